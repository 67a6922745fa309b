//! The exception classes of `_core` and the conversion of core errors into them; a value of
//! the wrong Python type anywhere in a configuration is a `ConfigTypeError` naming its field
//! path ([`extract_config`]).
use crate::error::{ConfigError as CoreConfigError, SimError};
use pyo3::create_exception;
use pyo3::exceptions::{PyAttributeError, PyRuntimeError, PyTypeError, PyValueError};
use pyo3::prelude::*;
use pyo3::sync::PyOnceLock;
use pyo3::types::{PyDict, PyTuple, PyType};

create_exception!(
    _core,
    ConfigError,
    PyValueError,
    "A configuration value outside its valid range (names the field, the value and the range)."
);
create_exception!(
    _core,
    SimulationError,
    PyRuntimeError,
    "A numerical failure during a simulation (carries the time `t_s` and the `state`)."
);

pub(crate) fn config_err(e: CoreConfigError) -> PyErr {
    Python::attach(|py| {
        let err = ConfigError::new_err(e.to_string());
        let v = err.value(py);
        let _ = v.setattr("field", e.field.clone());
        let _ = v.setattr("value", e.value.clone());
        let _ = v.setattr("expected", e.expected.clone());
        err
    })
}

pub(crate) fn sim_err(e: SimError) -> PyErr {
    if let SimError::Config(c) = &e {
        return config_err(c.clone());
    }
    let (t, state) = e.time_and_state();
    Python::attach(|py| {
        let err = SimulationError::new_err(e.to_string());
        let v = err.value(py);
        let _ = v.setattr("t_s", t);
        let _ = v.setattr("state", state);
        err
    })
}

/// The `ConfigTypeError` class: a `ConfigError` that is also a `TypeError` (a value of the
/// wrong Python type), created once per interpreter.
static CONFIG_TYPE_ERROR: PyOnceLock<Py<PyType>> = PyOnceLock::new();

pub(crate) fn config_type_error_class(py: Python<'_>) -> PyResult<&Bound<'_, PyType>> {
    CONFIG_TYPE_ERROR
        .get_or_try_init(py, || {
            let attrs = PyDict::new(py);
            attrs.set_item("__module__", "nanostage._core")?;
            attrs.set_item(
                "__doc__",
                "A configuration value of the wrong type (names the field path, the value, its \
                 type and the expected type); a ConfigError and a TypeError.",
            )?;
            let bases = PyTuple::new(
                py,
                [py.get_type::<ConfigError>(), py.get_type::<PyTypeError>()],
            )?;
            let class = py
                .get_type::<PyType>()
                .call1(("ConfigTypeError", bases, attrs))?
                .cast_into::<PyType>()?;
            Ok::<_, PyErr>(class.unbind())
        })
        .map(|c| c.bind(py))
}

/// `configuration` extracted as `T`. A value of the wrong type anywhere in it (a string or
/// `None` where the core expects a `Motor`, a float, ...) raises `ConfigTypeError` naming the
/// field path (`prefix` + the fields the extraction went through; `arg` when the object
/// itself is wrong), the value, its type and the expected type, e.g.
/// `plant.motor = 'abc' (str) is invalid: expected a Motor`.
pub(crate) fn extract_config<'py, T>(
    configuration: &Bound<'py, PyAny>,
    arg: &str,
    prefix: &str,
    expected: &str,
) -> PyResult<T>
where
    T: for<'a> FromPyObject<'a, 'py>,
{
    configuration.extract::<T>().map_err(|e| {
        let e: PyErr = e.into();
        type_error(configuration, arg, prefix, expected, e)
    })
}

/// The `ConfigTypeError` of a failed extraction `err` of `root` (see [`extract_config`]):
/// the derived extractions wrap an error in a field as "failed to extract field S.f" with the
/// inner error as its cause, so the cause chain gives the field path; walking `root` along it
/// gives the value, and the dataclass annotation of its field the expected type.
fn type_error(
    root: &Bound<'_, PyAny>,
    arg: &str,
    prefix: &str,
    expected: &str,
    err: PyErr,
) -> PyErr {
    let py = root.py();
    let mut names: Vec<String> = Vec::new();
    let mut cur = err;
    loop {
        let msg = cur.value(py).to_string();
        let Some(field) = msg.strip_prefix("failed to extract field ") else {
            break;
        };
        names.push(field.rsplit('.').next().unwrap_or(field).to_owned());
        match cur.cause(py) {
            Some(c) => cur = c,
            None => break,
        }
    }
    // Walk the object along the path as far as it goes.
    let mut value = root.clone();
    let mut parent: Option<(Bound<'_, PyAny>, &str)> = None;
    let mut walked: Vec<&str> = Vec::new();
    for name in &names {
        match value.getattr(name.as_str()) {
            Ok(v) => {
                parent = Some((value, name.as_str()));
                value = v;
                walked.push(name.as_str());
            }
            Err(_) => break,
        }
    }
    let field = if walked.is_empty() {
        arg.to_owned()
    } else {
        format!("{prefix}{}", walked.join("."))
    };
    let mut want = match &parent {
        Some((p, name)) => annotation(p, name).unwrap_or_else(|| "another type".to_owned()),
        None => expected.to_owned(),
    };
    // Say why when the innermost error is not about the type (e.g. a negative count).
    let inner = cur.value(py).to_string();
    let about_type =
        cur.is_instance_of::<PyAttributeError>(py) || cur.is_instance_of::<PyTypeError>(py);
    if !about_type && !inner.is_empty() {
        want = format!("{want} ({})", inner.lines().next().unwrap_or(&inner));
    }
    let mut shown = value
        .repr()
        .map_or_else(|_| "<unprintable>".to_owned(), |r| r.to_string());
    if shown.chars().count() > 80 {
        shown = shown.chars().take(77).collect::<String>() + "...";
    }
    let type_name = value
        .get_type()
        .name()
        .map_or_else(|_| "?".to_owned(), |n| n.to_string());
    let shown = format!("{shown} ({type_name})");
    let message = format!("{field} = {shown} is invalid: expected {want}");
    let made = config_type_error_class(py).and_then(|class| {
        let err = PyErr::from_type(class.clone(), message.clone());
        let v = err.value(py);
        v.setattr("field", field.clone())?;
        v.setattr("value", shown.clone())?;
        v.setattr("expected", want.clone())?;
        Ok(err)
    });
    made.unwrap_or_else(|e| e)
}

/// The expected type of field `name` of the dataclass `parent`, from its annotation:
/// "a Motor", "a float", "one of Plant, ForceDrivePlant".
fn annotation(parent: &Bound<'_, PyAny>, name: &str) -> Option<String> {
    let py = parent.py();
    let fields = py
        .import("dataclasses")
        .ok()?
        .call_method1("fields", (parent,))
        .ok()?;
    for f in fields.try_iter().ok()? {
        let f = f.ok()?;
        if f.getattr("name").ok()?.extract::<String>().ok()? != name {
            continue;
        }
        if let Some(choices) = literal_choices(parent, name) {
            return Some(format!("one of {choices}"));
        }
        let t = f.getattr("type").ok()?;
        let text = match t.extract::<String>() {
            Ok(s) => s,
            Err(_) => t
                .getattr("__name__")
                .and_then(|n| n.extract::<String>())
                .or_else(|_| t.str().map(|s| s.to_string()))
                .ok()?,
        };
        let parts: Vec<&str> = text.split('|').map(str::trim).collect();
        return Some(if parts.len() == 1 {
            let article = if text.starts_with(['A', 'E', 'I', 'O', 'U', 'a', 'e', 'i', 'o', 'u']) {
                "an"
            } else {
                "a"
            };
            format!("{article} {text}")
        } else {
            format!("one of {}", parts.join(", "))
        });
    }
    None
}

/// The choices of field `name` of `parent` when its annotation is a `Literal` (also through
/// an alias such as `AntiWindup`): `'none', 'clamp', 'conditional'`.
fn literal_choices(parent: &Bound<'_, PyAny>, name: &str) -> Option<String> {
    let typing = parent.py().import("typing").ok()?;
    let hint = typing
        .call_method1("get_type_hints", (parent.get_type(),))
        .ok()?
        .get_item(name)
        .ok()?;
    let origin = typing.call_method1("get_origin", (&hint,)).ok()?;
    if !origin.is(&typing.getattr("Literal").ok()?) {
        return None;
    }
    let args = typing.call_method1("get_args", (&hint,)).ok()?;
    let shown: Vec<String> = args
        .try_iter()
        .ok()?
        .filter_map(|a| a.ok()?.repr().ok().map(|r| r.to_string()))
        .collect();
    Some(shown.join(", "))
}
