"""The diagnosis's candidate fits on an executor (threads, processes, a Dask client) give the
results of the local run; the screening with the free nominal parameters held."""

from __future__ import annotations

import dataclasses as dc
import multiprocessing
from collections.abc import Callable
from concurrent.futures import Executor, ProcessPoolExecutor, ThreadPoolExecutor
from pathlib import Path
from typing import Any

import pytest
from diagnosis_cases import step_case

from nanostage.diagnosis.loop import diagnose_experiments
from nanostage.diagnosis.run import _setup
from nanostage.diagnosis.settings import DiagnosisSettings
from nanostage.effects import Effects, FrictionModifiers

#: Few starts, two rounds, two candidates: a few seconds per diagnosis.
FAST = DiagnosisSettings(n_starts_nominal=1, n_starts_candidate=1, forward_rounds=2, seed=3)
CANDIDATES = ["asymmetric_friction", "computation_delay"]


@pytest.fixture(scope="module")
def case(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Four short seed-axis steps (both directions) with a hidden friction asymmetry; two
    train, two validate; the Coulomb level free."""
    return step_case(
        tmp_path_factory.mktemp("executor"),
        Effects(motor_friction=FrictionModifiers(asymmetry=0.3)),
        seed=3,
        candidates=CANDIDATES,
        n_samples=250,
    )


def _diagnose(
    manifest: Path, executor: Any = None, settings: DiagnosisSettings = FAST
) -> dict[str, Any]:
    setup = _setup(manifest)
    return diagnose_experiments(
        setup.nominal,
        setup.free,
        setup.set_free,
        setup.folds,
        adapt=setup.adapt,
        candidates=CANDIDATES,
        settings=settings,
        progress=False,
        executor=executor,
    )


def _essence(out: dict[str, Any]) -> dict[str, Any]:
    """Everything a diagnosis decides and fits, as plain values (bit for bit)."""

    def fits(fs: Any) -> list[tuple[dict[str, float], dict[str, float], float]]:
        return [(f.values, f.std_errors, f.train_rms_m) for f in fs]

    return {
        "selected": out["selected"],
        "nominal": fits(out["nominal_fits"]),
        "final": fits(out["final_fits"]),
        "final_ms": out["final_validation_ms"].tolist(),
        "skipped": out["skipped"],
        "refit_control": out["refit_control"],
        "rounds": [
            [
                (
                    r.effect,
                    r.validation_ms.tolist(),
                    r.significant,
                    r.p_value,
                    r.setting,
                    r.log_occam,
                    fits(r.fold_fits),
                )
                for r in results
            ]
            for results in out["rounds"]
        ],
    }


@pytest.fixture(scope="module")
def local(case: Path) -> dict[str, Any]:
    return _essence(_diagnose(case))


def _threads() -> Executor:
    return ThreadPoolExecutor(max_workers=2)


def _processes() -> Executor:
    # Spawned workers: a forked child of a process whose core has started its threads
    # may wait for ever on a lock one of those threads held.
    return ProcessPoolExecutor(max_workers=2, mp_context=multiprocessing.get_context("spawn"))


class _Dask:
    """A ``dask.distributed.Client`` on an in-process cluster (threads), closed on exit."""

    def __enter__(self) -> Any:
        distributed = pytest.importorskip("distributed")
        self.client = distributed.Client(
            processes=False, n_workers=1, threads_per_worker=2, dashboard_address=None
        )
        return self.client

    def __exit__(self, *_: object) -> None:
        self.client.close()


@pytest.mark.parametrize(
    "make", [_threads, _processes, _Dask], ids=["threads", "processes", "dask"]
)
def test_candidate_fits_on_an_executor_give_the_local_results(
    case: Path, local: dict[str, Any], make: Callable[[], Any]
) -> None:
    """The same selection, fitted values, validation gaps and verdicts, to the last bit,
    whatever runs the candidates' fits (each fit has its own seed; the simulation cache of
    each task only saves repeats). The hidden asymmetry is found."""
    pytest.importorskip("cloudpickle")
    with make() as executor:
        remote = _essence(_diagnose(case, executor))
    assert remote == local
    assert local["selected"][:1] == ["asymmetric_friction"]


def test_the_local_results_do_not_depend_on_the_simulation_cache(
    case: Path, local: dict[str, Any]
) -> None:
    """A task's own cache (instead of the diagnosis's) changes nothing: neither does none."""
    assert _essence(_diagnose(case, settings=dc.replace(FAST, simulation_cache_mb=0.0))) == local


def test_an_executor_without_submit_is_rejected_before_fitting(case: Path) -> None:
    with pytest.raises(TypeError, match=r"executor must have a submit method .* not list"):
        _diagnose(case, executor=[])


def test_screening_holds_the_free_nominal_parameters_and_the_winner_is_refitted(
    case: Path,
) -> None:
    """With the nominal held in screening, a candidate known from its screening only keeps
    the model before's free values exactly (not fitted on them: no standard error); a
    winner is refitted with them free before it is selected, even when no candidate is
    refined otherwise. Without holding, every screened fit is a fit of them too."""
    out = _diagnose(case)
    assert FAST.screen_holds_nominal
    free = next(iter(out["nominal"].values))
    first = out["rounds"][0]
    # Two candidates, both among the best four: both refitted with the free value.
    assert all(free in r.fit.std_errors for r in first)
    none = dc.replace(FAST, refine_top=0, refine_best_friction_model=False, forward_rounds=1)
    held = _diagnose(case, settings=none)
    assert held["selected"] == ["asymmetric_friction"] and not held["refit_control"]
    warm = [f.values[free] for f in held["nominal_fits"]]
    for r in held["rounds"][0]:
        if r.effect in held["selected"]:
            assert free in r.fit.std_errors, r.effect
            assert r.fold_fits == held["final_fits"]
        else:
            assert free not in r.fit.std_errors, r.effect
            assert [f.values[free] for f in r.fold_fits] == warm
    moved = _diagnose(case, settings=dc.replace(none, screen_holds_nominal=False))["rounds"][0]
    assert all(free in r.fit.std_errors for r in moved)
    assert any([f.values[free] for f in r.fold_fits] != warm for r in moved)


def test_diagnose_passes_its_executor_to_the_candidate_fits(case: Path) -> None:
    """The user-facing ``diagnose(executor=)``: the same report as a local run (the
    selection, both gaps, every candidate's verdict)."""
    from nanostage.diagnosis.run import diagnose

    def essence(report: dict[str, Any]) -> Any:
        return (
            report["selected"],
            report["gap_before"]["total_rms_m"],
            report["gap_after"]["total_rms_m"],
            [(c["effect"], c["validation_rms_m"], c["significant"]) for c in report["candidates"]],
        )

    local_report = diagnose(case, None, settings=FAST, progress=False).report
    with _threads() as executor:
        remote_report = diagnose(
            case, None, settings=FAST, progress=False, executor=executor
        ).report
    assert essence(remote_report) == essence(local_report)
    assert local_report["selected"][:1] == ["asymmetric_friction"]


def test_cli_diagnose_spreads_the_fits_over_workers_or_a_scheduler(
    case: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``nanostage diagnose --workers N`` fits the candidates in N spawned processes and
    ``--scheduler ADDRESS`` on a Dask cluster: the same report as a local run (the fast
    settings patched in; the executor is what the CLI made, closed after)."""
    pytest.importorskip("cloudpickle")
    from nanostage import cli
    from nanostage.diagnosis import run

    real = run.diagnose
    seen: list[Any] = []

    def fast(manifest: Any, out_dir: Any, **kw: Any) -> Any:
        seen.append(kw["executor"])
        return real(manifest, out_dir, **{**kw, "settings": FAST})

    monkeypatch.setattr(run, "diagnose", fast)

    def essence(out: Path) -> Any:
        import json

        r = json.loads((out / "report.json").read_text(encoding="utf-8"))
        return (
            r["selected"],
            r["gap_after"]["total_rms_m"],
            [(c["effect"], c["validation_rms_m"]) for c in r["candidates"]],
        )

    base = ["diagnose", str(case), "--quiet", "--no-plot", "--out"]
    assert cli.main([*base, str(tmp_path / "local")]) == 0
    assert cli.main([*base, str(tmp_path / "pool"), "--workers", "2"]) == 0
    pool = seen[1]
    assert isinstance(pool, ProcessPoolExecutor)
    assert pool._mp_context.get_start_method() == "spawn"
    with pytest.raises(RuntimeError):  # shut down when the command ends
        pool.submit(int)
    assert essence(tmp_path / "pool") == essence(tmp_path / "local")
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(
        processes=False, n_workers=1, threads_per_worker=2, dashboard_address=None
    ) as cluster:
        address = cluster.scheduler_address
        assert cli.main([*base, str(tmp_path / "dask"), "--scheduler", address]) == 0
    assert isinstance(seen[2], distributed.Client)
    assert essence(tmp_path / "dask") == essence(tmp_path / "local")


def test_cli_diagnose_workers_out_of_range_is_named_before_any_work(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A bad --workers is an error naming the option, the value and the range, before the
    manifest (here: none) is read."""
    from nanostage import cli

    missing = str(tmp_path / "absent.toml")
    assert cli.main(["diagnose", missing, "--workers", "0"]) == 2
    err = capsys.readouterr().err
    assert "--workers = 0 is invalid: expected an integer in [1, 256]" in err
    assert "absent.toml" not in err
    assert cli.main(["diagnose", missing, "--workers", "2", "--scheduler", "tcp://h:1"]) == 2
    assert "not allowed with argument --workers" in capsys.readouterr().err
