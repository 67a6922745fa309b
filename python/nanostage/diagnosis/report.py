"""Write the diagnosis report: ``report.json``, ``report.md`` and figures.

Everything takes plain dicts and arrays so that the fitting engine can call it with what it
has. The report dict has the keys

``gap_before``, ``gap_after``
    :meth:`nanostage.diagnosis.gap.GapAnalysis.to_dict` (or a bare
    :meth:`~nanostage.diagnosis.gap.GapStats.to_dict`) before and after the fit;
``candidates``
    the ranked candidates, a list of dicts (any keys; rendered as a table in list order);
``selected``
    the selected effects: a list of names, a list of dicts or a dict;
any other key
    kept in ``report.json``; scalars and short lists are also listed in ``report.md``.

NaN and infinities become ``null`` in JSON; numpy scalars and arrays become numbers and
lists. matplotlib (the optional ``plot`` extra) is imported only by the figure functions,
which draw with the Agg backend and never show windows.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final

import numpy as np

from ..output import to_jsonable, write_json
from .segments import PHASES
from .signatures import SIGNATURE_UNITS

__all__ = [
    "FIGURE_NAMES",
    "JSON_NAME",
    "MARKDOWN_NAME",
    "PHASE_COLOURS",
    "ReportFiles",
    "markdown_report",
    "plot_gap_map",
    "plot_residual_spectrum",
    "to_jsonable",
    "write_json",
    "write_report",
]

#: File names written by :func:`write_report`.
JSON_NAME: Final = "report.json"
MARKDOWN_NAME: Final = "report.md"
FIGURE_NAMES: Final[Mapping[str, str]] = {
    "gap_map": "gap_map.png",
    "residual_spectrum": "residual_spectrum.png",
}
#: Band colour of each phase in the gap map.
PHASE_COLOURS: Final[Mapping[str, str]] = {
    "acceleration": "#8dd3c7",
    "slew": "#ffffb3",
    "braking": "#bebada",
    "overshoot": "#fb8072",
    "settling": "#80b1d3",
    "hold": "#d9d9d9",
}

_UM: Final = 1e6


# --------------------------------------------------------------------------------------------
# Markdown
# --------------------------------------------------------------------------------------------


def _num(v: Any) -> float | None:
    if isinstance(v, bool) or v is None:
        return None
    if isinstance(v, int | float | np.integer | np.floating):
        f = float(v)
        return f if math.isfinite(f) else None
    return None


def _fmt(key: str, v: Any) -> str:
    """A cell: lengths in µm, times in ms, speeds in mm/s, shares in %, by key suffix."""
    if v is None:
        return "—"
    if isinstance(v, bool):
        return "yes" if v else "no"
    f = _num(v)
    if f is None:
        if isinstance(v, float | np.floating):
            return "—"
        if isinstance(v, Mapping | list | tuple):
            return _md_escape(json.dumps(to_jsonable(v), ensure_ascii=False))
        return _md_escape(str(v))
    if key.endswith("_m_per_s"):
        return f"{f * 1e3:.4g}"
    if key.endswith("_m2"):
        return f"{f * 1e12:.4g}"
    if key.endswith("_m"):
        return f"{f * _UM:.4g}"
    if key.endswith("_s"):
        return f"{f * 1e3:.4g}"
    if key in ("share", "lead_share") or key.endswith("_share"):
        return f"{100.0 * f:.1f} %"
    if isinstance(v, int | np.integer):
        return str(int(v))
    return f"{f:.4g}"


def _unit(key: str) -> str:
    if key.endswith("_m_per_s"):
        return " [mm/s]"
    if key.endswith("_m2"):
        return " [µm²]"
    if key.endswith("_m"):
        return " [µm]"
    if key.endswith("_s"):
        return " [ms]"
    return ""


def _md_escape(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def _table(head: Sequence[str], rows: Sequence[Sequence[str]], align: str = "---") -> str:
    lines = ["| " + " | ".join(head) + " |", "| " + " | ".join([align] * len(head)) + " |"]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines) + "\n"


def _gap_stats(gap: Any) -> Mapping[str, Any] | None:
    """The overall GapStats dict of a GapAnalysis dict (or a GapStats dict itself)."""
    if not isinstance(gap, Mapping):
        return None
    if "overall" in gap and isinstance(gap["overall"], Mapping):
        overall: Mapping[str, Any] = gap["overall"]
        return overall
    if "partitions" in gap:
        return gap
    return None


def _gap_table(
    before: Mapping[str, Any] | None,
    after: Mapping[str, Any] | None,
    single: tuple[str, Mapping[str, Any]] | None = None,
) -> str:
    """The per-segment table: RMS and share before (the nominal model) and after (the
    selected set), with ``single`` = (effect, its gap stats) also the best single effect's
    columns between them."""
    cols: list[tuple[str, Mapping[str, Any]]] = [("before", before or {})]
    if single is not None:
        cols.append((f"{_md_escape(single[0])} alone", single[1]))
    if after is not None:
        cols.append(("after", after))
    out: list[str] = []
    parts = [c.get("partitions", {}) for _, c in cols]
    head = ["Segment", "n"]
    for label, _ in cols:
        head += [f"RMS {label} [µm]", f"share {label}"]
    total = ["**total**", _fmt("n", (before or after or {}).get("n_samples"))]
    for i, (_, c) in enumerate(cols):
        # The before column may be absent (an empty mapping); the others are given.
        total += [_fmt("rms_m", c.get("rms_m")), "100.0 %" if i or before else "—"]
    pnames: list[str] = []
    for p in parts:
        pnames += [n for n in p if n not in pnames]
    for pname in pnames:
        segs = [p.get(pname, {}) for p in parts]
        names: list[str] = []
        for sg in segs:
            names += [k for k in sg if k not in names]
        rows = [total]
        for name in names:
            cells = [sg.get(name, {}) for sg in segs]
            n = next((c["n_samples"] for c in cells if "n_samples" in c), None)
            row = [_md_escape(name), _fmt("n", n)]
            for c in cells:
                row += [_fmt("rms_m", c.get("rms_m")), _fmt("share", c.get("share"))]
            rows.append(row)
        out.append(f"#### By {pname}\n\n" + _table(head, rows))
    return "\n".join(out)


def _records_table(records: Sequence[Any]) -> str:
    """A table of a list of dicts (columns: union of keys, preferred ones first)."""
    preferred = ("rank", "effect", "name", "score", "gap_rms_m", "rms_m", "improvement")
    keys: list[str] = [
        k for k in preferred if any(isinstance(r, Mapping) and k in r for r in records)
    ]
    for r in records:
        if isinstance(r, Mapping):
            keys += [str(k) for k in r if str(k) not in keys]
    if not keys:
        return "\n".join(f"{i + 1}. {_md_escape(str(r))}" for i, r in enumerate(records)) + "\n"
    head = ["#"] + [f"{k}{_unit(k)}" for k in keys]
    rows = []
    for i, r in enumerate(records):
        m = r if isinstance(r, Mapping) else {}
        rows.append([str(i + 1)] + [_fmt(k, m.get(k)) for k in keys])
    return _table(head, rows)


def _features_table(before: Any, after: Any) -> str:
    fb = before.get("features") if isinstance(before, Mapping) else None
    fa = after.get("features") if isinstance(after, Mapping) else None
    if not fb:
        return ""
    after_by_key = {
        (r["experiment"], r["move"], r["feature"]): r for r in (fa or []) if isinstance(r, Mapping)
    }
    head = ["Experiment", "Move", "Step [µm]", "Feature", "Measured", "Simulated before"]
    if fa:
        head.append("Simulated after")
    rows = []
    for r in fb:
        f = str(r["feature"])
        unit = _unit(f)
        row = [
            _md_escape(str(r["experiment"])),
            str(r["move"]),
            _fmt("step_m", r.get("step_m")),
            f"{f}{unit}",
            _fmt(f, r.get("measured")),
            _fmt(f, r.get("simulated")),
        ]
        if fa:
            ra = after_by_key.get((r["experiment"], r["move"], f), {})
            row.append(_fmt(f, ra.get("simulated")))
        rows.append(row)
    return _table(head, rows)


def _iso_table(before: Any, after: Any) -> str:
    ib = before.get("iso230_2") if isinstance(before, Mapping) else None
    ia = after.get("iso230_2") if isinstance(after, Mapping) else None
    if not ib:
        return ""
    symbols = ib.get("symbols", {})
    head = ["Symbol", "Measured [µm]", "Simulated before [µm]"]
    if ia:
        head.append("Simulated after [µm]")
    rows = []
    for key, v in ib.get("axis", {}).items():
        row = [
            str(symbols.get(key, key)),
            _fmt(key, v.get("measured")),
            _fmt(key, v.get("simulated")),
        ]
        if ia:
            row.append(_fmt(key, ia.get("axis", {}).get(key, {}).get("simulated")))
        rows.append(row)
    return _table(head, rows)


def _limit_cycles(gap: Any) -> str:
    moves = gap.get("moves") if isinstance(gap, Mapping) else None
    if not isinstance(moves, Mapping):
        return ""
    rows = []
    for exp, ms in moves.items():
        for m in ms:
            lc = m.get("limit_cycle")
            if lc:
                rows.append(
                    [
                        _md_escape(str(exp)),
                        str(m.get("index")),
                        _fmt("amplitude_m", lc.get("amplitude_m")),
                        _fmt("period_s", lc.get("period_s")),
                    ]
                )
    if not rows:
        return "No limit cycle detected in hold (measured).\n"
    return _table(["Experiment", "Move", "Amplitude [µm]", "Period [ms]"], rows)


def _signature_value(unit: str, v: Any) -> str:
    """A signature feature's value: lengths in µm, the rest in their own unit."""
    f = _num(v)
    if f is None:
        return "—"
    return f"{f * _UM:.4g}" if unit == "m" else f"{f:.4g}"


def _signatures(sig: Any) -> str:
    """The report's ``signatures`` as a table: each feature measured (± its standard
    error) and simulated by each compared model, and each model's χ² from the measured."""
    if not isinstance(sig, Mapping) or not isinstance(sig.get("measured"), Mapping):
        return ""
    measured = sig["measured"]
    models = [m for m in sig.get("models") or [] if isinstance(m, Mapping)]

    def label(m: Mapping[str, Any]) -> str:
        eff = m.get("effect")
        return f"`{_md_escape(str(eff))}`" if eff else _md_escape(str(m.get("model")))

    def cell(d: Any, unit: str, with_error: bool) -> str:
        if not isinstance(d, Mapping):
            return "—"
        v = _signature_value(unit, d.get("value"))
        se = _num(d.get("std_error"))
        return f"{v} ± {_signature_value(unit, se)}" if with_error and se is not None else v

    head = ["Feature", "measured", *(label(m) for m in models)]
    rows = []
    for key, d in measured.items():
        unit = str(d.get("unit", "")) if isinstance(d, Mapping) else ""
        name = key + ("" if unit in ("", "-") else f" [{'µm' if unit == 'm' else unit}]")
        rows.append(
            [
                _md_escape(name),
                cell(d, unit, True),
                *(
                    cell((m.get("features") or {}).get(key), unit, False)
                    if "error" not in m
                    else "failed"
                    for m in models
                ),
            ]
        )
    rows.append(
        [
            "χ² from measured",
            "0",
            *(
                "—" if _num(m.get("distance")) is None else f"{_num(m.get('distance')):.3g}"
                for m in models
            ),
        ]
    )
    return (
        "Physical marks of the effects, measured directly on the traces (all experiments): "
        "limit cycles in holds (share of holds, size, frequency), the command at rest and "
        "on ramps by direction, the breakaway against the rest before a move. The χ² "
        "compares each model's simulated features with the measured ones in units of both "
        "standard errors: where the gap cannot tell candidates apart, the smaller χ² is "
        "the better match of these marks.\n\n" + _table(head, rows)
    )


def _nm(v: Any) -> str:
    f = _num(v)
    return "—" if f is None else f"{f * 1e9:.1f}"


def _fixed3(v: Any) -> str:
    f = _num(v)
    return "—" if f is None else f"{f:.3f}"


def _pct(v: Any) -> str:
    f = _num(v)
    return "—" if f is None else f"{100.0 * f:.1f} %"


def _value(v: Any) -> str:
    """A parameter value (4 significant digits)."""
    f = _num(v)
    return _md_escape(str(v)) if f is None else f"{f:.4g}"


def _estimate(d: Any) -> list[str]:
    """A parameter's ``{value, std_error}`` (or a bare value) as two table cells."""
    d = d if isinstance(d, Mapping) else {"value": d}
    se = _num(d.get("std_error"))
    return [_value(d.get("value")), "—" if se is None else f"{se:.3g}"]


def _parameters(params: Any) -> str:
    """``name = value ± std. error unit`` per parameter (the effect's prefix dropped),
    joined for a table cell."""
    if not isinstance(params, Mapping) or not params:
        return "—"
    cells = []
    for name, d in params.items():
        short = str(name).split(".", 1)[-1]
        if not isinstance(d, Mapping):
            cells.append(f"{_md_escape(short)} = {_value(d)}")
            continue
        se = _num(d.get("std_error"))
        unit = d.get("unit")
        err = "" if se is None else f" ± {se:.2g}"
        # A unit that only repeats the name (a delay's "samples") is left out.
        shown = unit and unit not in ("-", short)
        cells.append(
            f"{_md_escape(short)} = {_value(d.get('value'))}{err}"
            + (f" {_md_escape(str(unit))}" if shown else "")
        )
    return "<br>".join(cells)


def _is_diagnosis_candidate(c: Any) -> bool:
    return isinstance(c, Mapping) and "effect" in c and "validation_rms_m" in c


def _candidates_table(cands: Sequence[Mapping[str, Any]]) -> str:
    """The diagnosis's candidates (in the report's ranking order): gaps in nm (pooled RMS
    and the geometric mean over the validation experiments), shrinks in % (of both), parameters with
    errors, the reasons in words (the per-experiment gaps are in report.json)."""
    head = [
        "#",
        "effect",
        "validation gap [nm]",
        "geometric gap [nm]",
        "shrink",
        "geometric shrink",
        "significant",
        "p",
        "training gap [nm]",
        "log Occam",
        "parameters (± std. error)",
        "why",
    ]
    rows = []
    for i, c in enumerate(cands):
        p = _num(c.get("p_value"))
        occam = _num(c.get("log_occam_factor"))
        why = c.get("why")
        rows.append(
            [
                str(i + 1),
                f"`{_md_escape(str(c.get('effect')))}`",
                _nm(c.get("validation_rms_m")),
                _nm(c.get("validation_geometric_rms_m")),
                _pct(c.get("shrink")),
                _pct(c.get("geometric_shrink")),
                _fmt("significant", bool(c.get("significant"))),
                "—" if p is None else f"{p:.3f}",
                _nm(c.get("train_rms_m")),
                "—" if occam is None else f"{occam:.2f}",
                _parameters(c.get("parameters")),
                _md_escape("; ".join(str(w) for w in why))
                if isinstance(why, list | tuple)
                else _fmt("why", why),
            ]
        )
    return _table(head, rows)


def _summary(report: Mapping[str, Any], sb: Any, sa: Any) -> str:
    """The first lines: what was selected, the validation gap before and after, the
    cross-fitted shrink, the noise floor and what remains unexplained."""
    lines = []
    sel = report.get("selected")
    if isinstance(sel, list | tuple) and all(isinstance(x, str) for x in sel):
        lines.append(
            "- **Selected:** "
            + (
                ", ".join(f"`{_md_escape(x)}`" for x in sel)
                if sel
                else "none (no candidate shrinks the validation gap by more than noise "
                "and refitting alone do)"
            )
        )
    b = _num((sb or {}).get("rms_m")) if isinstance(sb, Mapping) else None
    a = _num((sa or {}).get("rms_m")) if isinstance(sa, Mapping) else None
    if b is not None and a is not None:
        shrink = f" (shrink {1.0 - a / b:.1%})" if b > 0 else ""
        lines.append(
            f"- **Validation gap** (all validation samples pooled): {b * 1e9:.1f} → "
            f"{a * 1e9:.1f} nm RMS{shrink}"
        )
    cf = report.get("crossfit")
    if isinstance(cf, Mapping) and _num(cf.get("shrink")) is not None:
        lines.append(
            f"- **Cross-fitted** (each validation experiment judged by models refitted on "
            f"all the others): {_nm(cf.get('gap_before_rms_m'))} → "
            f"{_nm(cf.get('gap_after_rms_m'))} nm (shrink {float(cf['shrink']):.1%})"
        )
    floor = _num(report.get("noise_floor_rms_m"))
    if floor is not None:
        text = f"- **Noise floor:** {floor * 1e9:.1f} nm RMS"
        un = _num(report.get("unexplained_rms_m"))
        if un is not None:
            text += f"; unexplained above it: {un * 1e9:.1f} nm"
        ex = _num(report.get("explained_fraction"))
        if ex is not None:
            text += f" ({ex:.0%} of the gap above the floor explained)"
        lines.append(text)
    scatter = report.get("level_scatter")
    if isinstance(scatter, Mapping) and _num(scatter.get("spread")) is not None:
        discounted = scatter.get("discounted") or {}
        lines.append(
            f"- **Run-to-run friction scatter:** {float(scatter['spread']):.3g} (relative "
            f"level, assumed: `level_scatter`); in {len(discounted)} experiment(s) the fits "
            "and judgements allow each run a level of its own within it (the gaps shown are "
            "as measured, a candidate's validation RMS and shrink are those of the "
            "discounted gaps)"
        )
    un_gap = report.get("unexplained")
    if isinstance(un_gap, Mapping) and _num(un_gap.get("gap_rms_m")) is not None:
        parts = [
            f"`{_md_escape(str(c.get('effect')))}` (shrink {float(c.get('shrink', 0.0)):.0%}"
            + (
                f", geometric {float(c['geometric_shrink']):.0%}"
                if _num(c.get("geometric_shrink")) is not None
                else ""
            )
            + (f", judged on {c['judged']}" if isinstance(c.get("judged"), str) else "")
            + ")"
            for c in un_gap.get("partial_explanations") or []
            if isinstance(c, Mapping) and _num(c.get("shrink")) is not None
        ]
        lines.append(
            f"- **Unexplained gap** of {float(un_gap['gap_rms_m']) * 1e9:.1f} nm RMS "
            f"({_num(un_gap.get('floor_ratio')) or 0.0:.1f}× the noise floor): no candidate "
            "explains it by the selection rules; best partial explanations: "
            + (", ".join(parts) if parts else "none (no candidate shrinks it)")
        )
    bounds = report.get("calibration_at_bounds")
    at = bounds.get("nominal") if isinstance(bounds, Mapping) else None
    if isinstance(at, list | tuple) and at and all(isinstance(r, Mapping) for r in at):
        lines.append(
            "- **Calibration at its bounds:** "
            + ", ".join(f"`{_md_escape(str(r.get('parameter')))}` ({r.get('bound')})" for r in at)
            + ": the nominal model bends these parameters to fit something it does not "
            "model, and the candidates are judged from that calibration"
            + (
                ", so an effect it has absorbed can be missed (see *Warnings*)"
                if not sel
                else " (see *Warnings*)"
            )
        )
    missed = _nominal_misses(report.get("signatures"))
    if missed:
        lines.append(
            "- **Marks the calibrated nominal model misses** (more than 3 standard errors; "
            "see *Signatures*): " + missed
        )
    folds = report.get("folds")
    if isinstance(folds, list | tuple) and folds and all(isinstance(f, Mapping) for f in folds):
        n_t = sum(len(f.get("train", [])) for f in folds)
        n_v = sum(len(f.get("validate", [])) for f in folds)
        lines.append(
            f"- **Experiments:** {len(folds)} fold(s), {n_t} training and {n_v} validation "
            "experiment(s) in all"
        )
    t = _num(report.get("timing_s"))
    spent, total = _phase_rows(report.get("phases"))
    if spent:
        lines.append(f"- **Time:** {total:.1f} s (see *Where the time went*)")
    elif t is not None:
        lines.append(f"- **Time:** {t:.1f} s")
    return "\n".join(lines) + "\n" if lines else ""


def _phase_rows(phases: Any) -> tuple[list[list[str]], float]:
    """The rows of *Where the time went* from the report's ``phases`` (the entries of a
    :class:`~.settings.PhaseClock`) and their total seconds; no rows (and 0) when there
    are none or they are malformed."""
    if not isinstance(phases, list | tuple) or not phases:
        return [], 0.0
    if not all(isinstance(e, Mapping) and _num(e.get("seconds")) is not None for e in phases):
        return [], 0.0
    total = sum(float(e["seconds"]) for e in phases)
    rows = []
    for e in phases:
        sec = float(e["seconds"])
        sims = e.get("simulated")
        rows.append(
            [
                _md_escape(str(e.get("phase", ""))),
                "—" if e.get("round") is None else str(e["round"]),
                f"{sec:.1f}",
                f"{sec / total:.0%}" if total > 0 else "—",
                "—" if sims is None else f"{int(sims):,}".replace(",", " "),
            ]
        )
    return rows, total


def _cross_judged_table(rounds: Any) -> str:
    """The report's ``cross_judged`` as one table (round, effect, geometric shrink, p,
    significant, and why not: the rules a candidate failed); empty without entries."""

    def why_not(c: Mapping[str, Any]) -> str:
        why = c.get("why")
        if c.get("significant") or not isinstance(why, list | tuple):
            return "—"
        return "; ".join(_md_escape(str(w)) for w in why) or "—"

    rows = [
        [
            str(r.get("round")),
            f"`{_md_escape(str(c.get('effect')))}`",
            _pct(c.get("geometric_shrink")),
            _fixed3(c.get("p_value")),
            "yes" if c.get("significant") else "no",
            why_not(c),
        ]
        for r in (rounds if isinstance(rounds, list | tuple) else [])
        if isinstance(r, Mapping)
        for c in r.get("candidates") or []
        if isinstance(c, Mapping)
    ]
    if not rows:
        return ""
    return _table(["round", "effect", "geometric shrink", "p", "significant", "why not"], rows)


def _extra_refit_lines(refits: Any) -> list[str]:
    """One line per round that refitted candidates beyond the usual refits, and why
    (report ``extra_refits``)."""
    out: list[str] = []
    for d in refits if isinstance(refits, list | tuple) else []:
        why = []
        if d.get("at_bounds"):
            why.append("has " + ", ".join(f"`{_md_escape(str(p))}`" for p in d["at_bounds"]))
            why[-1] += " at a bound"
        if d.get("missed_marks"):
            marks = ", ".join(f"`{_md_escape(str(m))}`" for m in d["missed_marks"])
            why.append(f"misses the marks {marks} (see *Signatures*)")
        names = ", ".join(f"`{_md_escape(str(n))}`" for n in d.get("refined") or []) or "none"
        skipped = ", ".join(f"`{_md_escape(str(n))}`" for n in d.get("not_refined") or [])
        out.append(
            f"Round {d.get('round')}: the model before {' and '.join(why)}, so the effects "
            f"that make {'them' if d.get('missed_marks') else 'it'} were refitted with the free "
            f"parameters too: {names}"
            + (f" (not {skipped}: screened far worse than the model before)" if skipped else "")
            + ".\n"
        )
    return out


def _mark_support_lines(support: Any) -> list[str]:
    """One line per round whose friction laws put right the ramp marks the model before
    misses (report ``speed_mark_support``)."""
    out: list[str] = []
    for d in support if isinstance(support, list | tuple) else []:
        laws = d.get("laws") if isinstance(d, Mapping) else None
        if not isinstance(laws, Mapping) or not laws:
            continue
        names = ", ".join(f"`{_md_escape(str(n))}` {float(v):.0%}" for n, v in laws.items())
        out.append(
            f"Round {d.get('round')}: the model before misses the ramp marks of the "
            f"friction's speed dependence, and these friction laws' fits remove most of their "
            f"χ² ({names}): the friction-law share rule does not hold them back.\n"
        )
    return out


def _tie_entry(report: Mapping[str, Any], effect: str) -> Mapping[str, Any] | None:
    """The ``tie_signatures`` entry of the round that selected ``effect``, or None."""
    sel = report.get("selected") or []
    rounds = report.get("tie_signatures") or []
    if effect not in sel or not isinstance(rounds, list | tuple):
        return None
    rnd = list(sel).index(effect) + 1
    return next(
        (r for r in rounds if isinstance(r, Mapping) and r.get("round") == rnd),
        None,
    )


def _settled_by_marks(report: Mapping[str, Any], effect: str) -> bool:
    """Whether the signature judge left the selected ``effect`` alone in its tie: every
    other candidate's χ² beyond the smallest by more than the round's ``margin``."""
    entry = _tie_entry(report, effect)
    d = None if entry is None else entry.get("distances")
    margin = None if entry is None else entry.get("margin")
    if not isinstance(d, Mapping) or effect not in d or not isinstance(margin, int | float):
        return False
    closest = min(float(v) for v in d.values())
    others = [float(v) for k, v in d.items() if k != effect]
    return bool(others) and all(v > closest + margin for v in others)


def _tie_signatures(report: Mapping[str, Any], effect: str) -> str:
    """The signature χ² of the candidates tied with a selected ``effect`` (its round's
    entry of ``tie_signatures``), in words; empty without one."""
    entry = _tie_entry(report, effect)
    d = None if entry is None else entry.get("distances")
    if not isinstance(d, Mapping) or len(d) < 2:
        return ""
    parts = ", ".join(
        f"`{_md_escape(str(k))}` {float(v):.3g}" for k, v in sorted(d.items(), key=lambda kv: kv[1])
    )
    marks = entry.get("marks") if entry is not None else None
    on = (
        " on the marks the tied effects make ("
        + (", ".join(f"`{_md_escape(str(m))}`" for m in marks) or "none")
        + ")"
        if isinstance(marks, list | tuple)
        else ""
    )
    return (
        f"; signature χ² against the measured marks{on}: {parts} (each mark in units of the "
        "closest tied model's miss of it; those within `signature_margin` of the smallest "
        "stay in the tie)"
    )


def _nominal_misses(sig: Any, top: int = 4) -> str:
    """The signature features the calibrated nominal model misses, in words."""
    if not isinstance(sig, Mapping):
        return ""
    nominal = next(
        (
            m
            for m in sig.get("models") or []
            if isinstance(m, Mapping) and m.get("model") == "nominal"
        ),
        None,
    )
    if nominal is None:
        return ""
    parts = []
    for d in (nominal.get("misses") or [])[:top]:
        key = str(d.get("feature"))
        unit = SIGNATURE_UNITS.get(key, "")
        shown = "µm" if unit == "m" else unit
        tail = "" if shown in ("", "-") else f" {shown}"
        parts.append(
            f"`{_md_escape(key)}` measured {_signature_value(unit, d.get('measured'))}{tail}, "
            f"simulated {_signature_value(unit, d.get('simulated'))}{tail} "
            f"({float(d.get('z', 0.0)):+.1f}σ)"
        )
    return "; ".join(parts)


def _evidence(evidence: Sequence[Any]) -> str:
    """Per selected effect: how much it shrank the gap against the model before, which
    segments it fixed, its parameters with their errors (a tie is stated in the list of
    selected effects above it)."""
    out = []
    for i, ev in enumerate(evidence):
        if not isinstance(ev, Mapping):
            continue
        name = str(ev.get("effect"))
        rnd = ev.get("round", i + 1)
        out.append(f"### {i + 1}. `{_md_escape(name)}` (round {rnd})\n")
        items = []
        for w in ev.get("why") or []:
            items.append(f"- {_md_escape(str(w))}")
        fixed = ev.get("segments_fixed") or []
        if fixed:
            items.append(
                "- Segments it fixed most: " + "; ".join(_md_escape(str(x)) for x in fixed)
            )
        lb, la = _num(ev.get("lead_share_before")), _num(ev.get("lead_share_after"))
        if lb is not None and la is not None:
            items.append(
                f"- Residual power near the screw lead's spatial period: {lb:.1%} → {la:.1%}"
            )
        out.append("\n".join(items) + "\n")
        params = ev.get("parameters")
        if isinstance(params, Mapping) and params:
            rows = [
                [
                    f"`{_md_escape(str(pname))}`",
                    *_estimate(d),
                    _md_escape(str((d if isinstance(d, Mapping) else {}).get("unit") or "—")),
                ]
                for pname, d in params.items()
            ]
            out.append(_table(["parameter", "value", "std. error", "unit"], rows))
    return "\n".join(out)


def _advice(advice: Sequence[Any]) -> str:
    if not advice:
        return (
            "None of the design checks found a gap: both directions and reversals, dwells "
            "at least a factor 2 apart, the command logged, ramps at several speeds, "
            "micro-steps, a travel of two screw leads, validation where training ran and "
            "spread over several experiments, and a repeat are there, and no two "
            "significant candidates fit the validation data equally well. Whether an "
            "effect's marks are large enough to see in these experiments is not judged "
            "here (an effect that is there can still leave them below the noise).\n"
        )
    lines = []
    for a in advice:
        if not isinstance(a, Mapping):
            lines.append(f"- {_md_escape(str(a))}")
            continue
        effects = ", ".join(f"`{_md_escape(str(e))}`" for e in a.get("effects") or [])
        lines.append(
            f"- {effects + ': ' if effects else ''}{_md_escape(str(a.get('issue', '')))}. "
            f"**Experiment:** {_md_escape(str(a.get('experiment', '')))}"
        )
    return "\n".join(lines) + "\n"


def _forward_selection(rounds: Sequence[Any], selected: Sequence[Any], top: int = 4) -> str:
    """One row per round: what it selected, and its best candidates with their shrink."""
    rows = []
    for i, rnd in enumerate(rounds):
        if not isinstance(rnd, Mapping):
            continue
        cands = [c for c in rnd.get("candidates") or [] if isinstance(c, Mapping)]
        pick = selected[i] if i < len(selected) else None
        best = ", ".join(
            f"`{_md_escape(str(c.get('effect')))}` {_pct(c.get('shrink'))}"
            + ("" if c.get("significant") else " (n.s.)")
            for c in cands[:top]
        )
        rows.append(
            [
                str(rnd.get("round", i + 1)),
                "—" if pick is None else f"`{_md_escape(str(pick))}`",
                best or "—",
            ]
        )
    return _table(["round", "selected", f"best {top} (shrink against the model before)"], rows)


def markdown_report(
    report: Mapping[str, Any],
    *,
    title: str = "Sim-to-real gap diagnosis",
    figures: Mapping[str, str] | None = None,
) -> str:
    """The Markdown report: gap per segment before/after, candidates ranked, selected
    effects, response features and ISO 230-2 measured vs simulated, limit cycles, the lead
    share, other scalar entries, and links to the figures.

    Parameters
    ----------
    report : mapping
        See the module docstring.
    title : str
        Top heading.
    figures : mapping of str to str, optional
        Figure label → relative path, linked at the end.
    """
    before, after = report.get("gap_before"), report.get("gap_after")
    sb, sa = _gap_stats(before), _gap_stats(after)
    # The best single effect gets columns of its own where they differ from the after
    # ones: with more than one effect selected, or none (the best any single effect did).
    ss = _gap_stats(report.get("gap_best_single"))
    name = report.get("best_single_effect")
    single = (
        (str(name), ss)
        if ss is not None and name and len(report.get("selected") or []) != 1
        else None
    )
    out = [f"# {_md_escape(title)}\n"]
    summary = _summary(report, sb, sa)
    if summary:
        out.append(summary)
    if "selected" in report:
        out.append("## Selected\n")
        sel = report["selected"]
        ties = report.get("indistinguishable") or {}
        if isinstance(sel, Mapping):
            out.append(_records_table([sel]))
        elif isinstance(sel, list | tuple) and sel and all(isinstance(s, Mapping) for s in sel):
            out.append(_records_table(list(sel)))
        elif isinstance(sel, list | tuple):
            out.append(
                "\n".join(
                    f"- `{_md_escape(str(s))}`"
                    + (
                        " — the validation data cannot tell it from "
                        + ", ".join(f"`{_md_escape(t)}`" for t in ties[s])
                        + " (see the advice)"
                        + _tie_signatures(report, s)
                        + (
                            "; selected by these marks (the others beyond the margin)"
                            if _settled_by_marks(report, s)
                            else "; selected by the larger Occam factor (its parameters "
                            "pinned down to a larger share of their bounds)"
                            if report.get("tie_break") == "occam_factor"
                            else (
                                "; selected by the smaller validation gap"
                                if report.get("ranking", "pooled") == "pooled"
                                else "; selected by the smaller geometric validation gap"
                            )
                        )
                        if isinstance(ties, Mapping) and ties.get(s)
                        else ""
                    )
                    for s in sel
                )
                + "\n"
                if sel
                else "None.\n"
            )
        else:
            out.append(f"{_md_escape(str(sel))}\n")
        evidence = report.get("evidence")
        if isinstance(evidence, list | tuple) and evidence:
            out.append(
                "What each selected effect fixed, against the model before it was added "
                "(validation gaps here and in the candidates count each validation "
                "experiment's mean square equally, so they differ from the pooled gap of "
                "the summary), and its identified parameters (standard errors from the "
                "fit's Jacobian, inflated for correlated residuals).\n"
            )
            out.append(_evidence(evidence))
    model_file = report.get("model_file")
    if isinstance(model_file, str):
        out.append("## Model file\n")
        out.append(
            f"`{_md_escape(model_file)}`: the selected model (the nominal parameters as "
            "refitted with the selected effects, and the effects at their fitted values), "
            "the model behind the gap after; load it with `nanostage.load_model` or pass it "
            "as `--model` (docs/model-file.md).\n"
        )
    warns = report.get("warnings")
    if isinstance(warns, list | tuple) and warns:
        out.append("## Warnings\n")
        out.append("\n".join(f"- {_md_escape(str(w))}" for w in warns) + "\n")
    if isinstance(report.get("advice"), list | tuple):
        out.append("## Experiment advice\n")
        out.append(_advice(report["advice"]))
    if sb is not None or sa is not None:
        out.append("## Gap per segment\n")
        out.append(
            "RMS residual (measured − simulated) per segment and its share of the total sum "
            "of squares (the shares of each partition add up to 100 %)"
            + (
                f"; before: the nominal model, {_md_escape(str(name))} alone: the best single "
                "effect, after: the selected set"
                if single is not None
                else ""
            )
            + ".\n"
        )
        out.append(_gap_table(sb, sa, single))
    lead_rows = []
    for label, g in (("before", before), ("after", after)):
        if isinstance(g, Mapping) and "lead_share" in g:
            lead = _num(g.get("lead_m"))
            period = "—" if lead is None else f"{lead * 1e3:g}"
            lead_rows.append([label, period, _fmt("share", g.get("lead_share"))])
    if lead_rows:
        out.append("## Position-periodic residual\n")
        out.append(
            "Share of the spatial residual power within ±15 % of the screw-lead frequency "
            "(a large share points at position-dependent friction; — if the travel is too "
            "short).\n"
        )
        out.append(_table(["", "Period [mm]", "Power share"], lead_rows))
    cf = report.get("crossfit")
    if isinstance(cf, Mapping) and _num(cf.get("shrink")) is not None:
        b, a = _num(cf.get("gap_before_rms_m")), _num(cf.get("gap_after_rms_m"))
        out.append("## Cross-fit\n")
        out.append(
            f"Each validation experiment judged by the nominal and the selected model "
            f"refitted on all the other experiments ({cf.get('folds')} folds): the gap "
            f"that remains once the model is recalibrated on all the data.\n"
        )
        out.append(
            _table(
                ["", "Validation gap [nm]"],
                [
                    ["nominal", "—" if b is None else f"{b * 1e9:.1f}"],
                    ["selected", "—" if a is None else f"{a * 1e9:.1f}"],
                    ["shrink", f"{float(cf['shrink']):.1%}"],
                ],
            )
        )
    if "candidates" in report:
        out.append("## Candidates (ranked)\n")
        cands = list(report["candidates"])
        if cands and all(_is_diagnosis_candidate(c) for c in cands):
            order = (
                "best pooled validation gap first (the RMS over the validation experiments, "
                "each experiment's mean square counted equally)"
                if report.get("ranking", "pooled") == "pooled"
                else "best geometric gap first (the geometric mean over the validation "
                "experiments of their RMS gaps, each at least its noise floor: each "
                "experiment counts by the factor a candidate cuts its own gap above the "
                "floor; validation gap: the pooled RMS)"
            )
            out.append(
                f"Round 1: every candidate added to the calibrated nominal model alone, "
                f"{order}; shrink: the fraction of the pooled gap removed; log Occam: the "
                "tie-break, larger is simpler; the gap per validation experiment is in "
                "report.json.\n"
            )
            out.append(_candidates_table(cands))
            out.extend(_extra_refit_lines(report.get("extra_refits")))
            out.extend(_mark_support_lines(report.get("speed_mark_support")))
        else:
            out.append(_records_table(cands) if cands else "No candidates.\n")
    rounds = report.get("forward_selection")
    if isinstance(rounds, list | tuple) and rounds:
        sel = report.get("selected")
        out.append("## Forward selection\n")
        out.append(_forward_selection(rounds, sel if isinstance(sel, list | tuple) else []))
    refits = report.get("refit_control")
    if isinstance(refits, list | tuple) and refits:
        out.append("## Refit control\n")
        out.append(
            "The model before, refitted from a candidate's free values: where that fits "
            "the training experiments better and the validation experiments no worse it "
            "became the baseline of the round (refitting alone is not credited to an "
            "effect); a refit that predicts the validation experiments worse did not.\n"
        )
        out.append(
            _table(
                [
                    "round",
                    "restarted from",
                    "training gap [nm]",
                    "validation gap [nm]",
                    "baseline",
                ],
                [
                    [
                        str(r.get("round")),
                        f"`{_md_escape(str(r.get('restarted_from')))}`",
                        f"{_nm(r.get('train_rms_before_m'))} → {_nm(r.get('train_rms_after_m'))}",
                        f"{_nm(r.get('validation_rms_before_m'))} → "
                        f"{_nm(r.get('validation_rms_after_m'))}",
                        "yes" if r.get("adopted", True) else "no: validation worse",
                    ]
                    for r in refits
                    if isinstance(r, Mapping)
                ],
            )
        )
    judged = _cross_judged_table(report.get("cross_judged"))
    if judged:
        out.append("## Judged on every experiment\n")
        out.append(
            "Each round's refitted candidates, judged again on all experiments (training "
            "ones too), each held out once and judged by refits without it; the round "
            "selected the first significant one (see docs/diagnosis.md, *Cross-judging*).\n"
        )
        out.append(judged)
    nominal = report.get("nominal_parameters")
    if isinstance(nominal, Mapping) and nominal:
        with_effects = report.get("selected_model_parameters")
        with_effects = (
            with_effects if isinstance(with_effects, Mapping) and report.get("selected") else {}
        )
        out.append("## Calibrated nominal parameters\n")
        head = ["parameter (SI units)", "nominal model", "std. error"]
        if with_effects:
            out.append(
                "Calibrated on the training experiments: the nominal model alone, and "
                "refitted with the selected effects.\n"
            )
            head += ["with the selected effects", "std. error"]
        rows = [
            [
                f"`{_md_escape(str(pname))}`",
                *_estimate(d),
                *(_estimate(with_effects.get(pname)) if with_effects else []),
            ]
            for pname, d in nominal.items()
        ]
        out.append(_table(head, rows))
    feats = _features_table(before, after)
    if feats:
        out.append("## Response features, measured vs simulated\n")
        out.append(feats)
    iso = _iso_table(before, after)
    if iso:
        out.append("## ISO 230-2 (final hold positions)\n")
        out.append(iso)
    sig = _signatures(report.get("signatures"))
    if sig:
        out.append("## Signatures, measured vs models\n")
        out.append(sig)
    lc = _limit_cycles(before)
    if lc:
        out.append("## Limit cycles in hold\n")
        out.append(lc)
    spent, _ = _phase_rows(report.get("phases"))
    if spent:
        out.append("## Where the time went\n")
        out.append(
            "Wall time and simulations run per phase (a simulation: one experiment of one "
            "model; those looked up in the diagnosis's cache are not counted).\n"
        )
        out.append(_table(["phase", "round", "time [s]", "share", "simulations"], spent, "---:"))
    skipped = report.get("skipped")
    if isinstance(skipped, Mapping) and skipped:
        out.append("## Not fitted\n")
        out.append(
            _table(
                ["effect", "why"],
                [[f"`{_md_escape(str(k))}`", _md_escape(str(v))] for k, v in skipped.items()],
            )
        )
    known = {
        "model_file",
        "gap_before",
        "gap_after",
        "gap_best_single",
        "candidates",
        "selected",
        "indistinguishable",
        "tie_break",
        "tie_signatures",
        "extra_refits",
        "speed_mark_support",
        "measured_on_every",
        "cross_judged",
        "crossfit",
        "evidence",
        "advice",
        "forward_selection",
        "refit_control",
        "nominal_parameters",
        "selected_model_parameters",
        "skipped",
        "folds",
        "noise_floor_rms_m",
        "unexplained_rms_m",
        "unexplained",
        "warnings",
        "calibration_at_bounds",
        "explained_fraction",
        "signatures",
        "timing_s",
        "phases",
    }
    extra = [
        [_md_escape(str(k)) + _unit(str(k)), _fmt(str(k), v)]
        for k, v in report.items()
        if k not in known and (_num(v) is not None or isinstance(v, str | bool) or v is None)
    ]
    if extra:
        out.append("## Other\n")
        out.append(_table(["Key", "Value"], extra))
    if figures:
        out.append("## Figures\n")
        out.append("\n".join(f"![{_md_escape(k)}]({v})" for k, v in figures.items()) + "\n")
    return "\n".join(out)


# --------------------------------------------------------------------------------------------
# Figures
# --------------------------------------------------------------------------------------------


def _figure(size: tuple[float, float]) -> Any:
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError as e:  # pragma: no cover - exercised only without the extra
        raise ImportError("figures need matplotlib: pip install 'nanostage[plot]'") from e
    fig = Figure(figsize=size, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _intervals(exp: Mapping[str, Any], n: int) -> list[tuple[str, int, int]]:
    if "intervals" in exp:
        return [(str(p), int(a), int(b)) for p, a, b in exp["intervals"]]
    if "phase" in exp:
        ph = np.asarray(exp["phase"])
        labels = ph if ph.dtype.kind in "US" else np.asarray(PHASES)[ph.astype(np.int64)]
        cuts = np.flatnonzero(labels[1:] != labels[:-1]) + 1
        starts = np.concatenate(([0], cuts))
        ends = np.concatenate((cuts, [n]))
        return [(str(labels[a]), int(a), int(b)) for a, b in zip(starts, ends, strict=True)]
    return []


def plot_gap_map(
    experiments: Sequence[Mapping[str, Any]],
    path: str | Path | None = None,
    *,
    segment_rms_before_m: Mapping[str, float | None] | None = None,
    segment_rms_after_m: Mapping[str, float | None] | None = None,
    max_experiments: int = 6,
    title: str | None = None,
) -> Any:
    """The gap map: per experiment, measured vs simulated position (top) and the residual
    with the phase bands coloured (below); on the right, the RMS residual per phase.

    Parameters
    ----------
    experiments : sequence of mapping
        Per experiment: ``name``, ``time_s``, ``measured_m``, ``simulated_m``, optional
        ``reference_m``, ``simulated_after_m`` (the fitted simulation), and the phases as
        ``intervals`` (``(phase, first, end)`` runs) or ``phase`` (per-sample names or
        indices into :data:`~nanostage.diagnosis.segments.PHASES`).
        :meth:`~nanostage.diagnosis.gap.ExperimentGap.figure_data` gives this.
    path : str or Path, optional
        Save as PNG there.
    segment_rms_before_m, segment_rms_after_m : mapping of str to float, optional
        Phase → RMS residual, m, for the bar chart (e.g. ``gap["overall"]["partitions"]
        ["phase"]`` reduced to ``rms_m``).
    max_experiments : int
        Draw at most this many experiments (the first ones).
    title : str, optional

    Returns
    -------
    matplotlib.figure.Figure
    """
    exps = list(experiments)[: max(1, max_experiments)]
    if not exps:
        raise ValueError("no experiments to draw")
    has_bars = bool(segment_rms_before_m or segment_rms_after_m)
    fig = _figure((13.0 if has_bars else 10.0, 1.0 + 3.6 * len(exps)))
    gs = fig.add_gridspec(
        2 * len(exps),
        2 if has_bars else 1,
        width_ratios=[3, 1] if has_bars else None,
        height_ratios=[3, 2] * len(exps),
    )
    for i, e in enumerate(exps):
        t = np.asarray(e["time_s"], dtype=np.float64)
        meas = np.asarray(e["measured_m"], dtype=np.float64)
        sim = np.asarray(e["simulated_m"], dtype=np.float64)
        travel = float(np.ptp(meas))
        scale, unit = (1e3, "mm") if travel > 10e-3 else (_UM, "µm")
        top = fig.add_subplot(gs[2 * i, 0])
        bottom = fig.add_subplot(gs[2 * i + 1, 0], sharex=top)
        if "reference_m" in e:
            top.plot(t, np.asarray(e["reference_m"]) * scale, "k--", lw=0.8, label="reference")
        top.plot(t, meas * scale, lw=1.2, label="measured")
        top.plot(t, sim * scale, lw=1.0, label="simulated")
        after = e.get("simulated_after_m")
        if after is not None:
            top.plot(t, np.asarray(after) * scale, lw=1.0, ls="-.", label="simulated (fitted)")
        top.set_ylabel(f"position [{unit}]")
        top.set_title(str(e.get("name", f"experiment {i + 1}")), fontsize=10)
        top.grid(alpha=0.3)
        top.legend(loc="best", fontsize=7)
        seen: set[str] = set()
        for phase, a, b in _intervals(e, t.size):
            if a >= t.size:
                continue
            t1 = t[min(b, t.size - 1)]
            bottom.axvspan(
                t[a],
                t1,
                color=PHASE_COLOURS.get(phase, "#eeeeee"),
                alpha=0.6,
                lw=0,
                label=None if phase in seen else phase,
            )
            seen.add(phase)
        bottom.plot(t, (meas - sim) * _UM, lw=0.9, color="C3", label="residual")
        if after is not None:
            bottom.plot(
                t, (meas - np.asarray(after)) * _UM, lw=0.8, color="C2", label="residual (fitted)"
            )
        bottom.axhline(0.0, color="k", lw=0.5)
        bottom.set_ylabel("residual [µm]")
        bottom.set_xlabel("time [s]")
        bottom.grid(alpha=0.3)
        bottom.legend(loc="upper right", fontsize=6, ncol=4)
    if has_bars:
        ax = fig.add_subplot(gs[:, 1])
        names = list(PHASES)
        y = np.arange(len(names))
        h = 0.38
        for k, (label, vals) in enumerate(
            (("before", segment_rms_before_m), ("after", segment_rms_after_m))
        ):
            if not vals:
                continue
            width = [(_num(vals.get(n)) or 0.0) * _UM for n in names]
            ax.barh(
                y + (k - 0.5) * h,
                width,
                height=h,
                label=label,
                color=[PHASE_COLOURS[n] for n in names],
                edgecolor="k",
                hatch=None if k == 0 else "//",
            )
        ax.set_yticks(y, names)
        ax.invert_yaxis()
        ax.set_xlabel("RMS residual [µm]")
        ax.set_title("per phase", fontsize=10)
        ax.grid(alpha=0.3, axis="x")
        ax.legend(fontsize=8)
    if title:
        fig.suptitle(title)
    if path is not None:
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(path, dpi=110)
    return fig


def plot_residual_spectrum(
    time_spectrum: Mapping[str, Any] | None,
    spatial_spectrum: Mapping[str, Any] | None,
    path: str | Path | None = None,
    *,
    lead_m: float | None = None,
    time_spectrum_after: Mapping[str, Any] | None = None,
    spatial_spectrum_after: Mapping[str, Any] | None = None,
    title: str | None = None,
) -> Any:
    """Residual power spectra: vs frequency (left) and vs spatial frequency (right, the lead
    period marked).

    Parameters
    ----------
    time_spectrum, spatial_spectrum : mapping, optional
        ``{"frequency": array, "psd": array}`` (e.g.
        :meth:`~nanostage.diagnosis.gap.Spectrum.to_dict`); Hz and m²/Hz, or 1/m and m²·m.
    path : str or Path, optional
        Save as PNG there.
    lead_m : float, optional
        Spatial period to mark, m (the screw lead).
    time_spectrum_after, spatial_spectrum_after : mapping, optional
        The same after the fit, overlaid.

    Returns
    -------
    matplotlib.figure.Figure
    """
    fig = _figure((11.0, 4.0))
    ax_t, ax_x = fig.subplots(1, 2)

    def draw(ax: Any, spec: Mapping[str, Any] | None, xscale: float, label: str, ls: str) -> None:
        if not spec:
            return
        f = np.asarray(spec["frequency"], dtype=np.float64)
        p = np.asarray(spec["psd"], dtype=np.float64)
        ok = (f > 0) & (p > 0)
        if ok.any():
            ax.loglog(f[ok] * xscale, p[ok], ls, lw=1.0, label=label)

    draw(ax_t, time_spectrum, 1.0, "before", "-")
    draw(ax_t, time_spectrum_after, 1.0, "after", "--")
    ax_t.set_xlabel("frequency [Hz]")
    ax_t.set_ylabel("residual PSD [m²/Hz]")
    ax_t.set_title("in time", fontsize=10)
    draw(ax_x, spatial_spectrum, 1e-3, "before", "-")
    draw(ax_x, spatial_spectrum_after, 1e-3, "after", "--")
    ax_x.set_xlabel("spatial frequency [1/mm]")
    ax_x.set_ylabel("residual PSD [m²·m]")
    ax_x.set_title("in space (motion only)", fontsize=10)
    if not spatial_spectrum:
        ax_x.text(0.5, 0.5, "no motion stretches", transform=ax_x.transAxes, ha="center")
    if lead_m:
        f_lead = 1e-3 / lead_m
        ax_x.axvline(f_lead, color="r", ls=":", lw=1.0, label=f"lead {lead_m * 1e3:g} mm")
        lo, hi = ax_x.get_xlim()
        ax_x.set_xlim(min(lo, 0.5 * f_lead), max(hi, 2.0 * f_lead))
    for ax in (ax_t, ax_x):
        ax.grid(alpha=0.3, which="both")
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=8)
    if title:
        fig.suptitle(title)
    if path is not None:
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(path, dpi=110)
    return fig


# --------------------------------------------------------------------------------------------
# Everything
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True, kw_only=True)
class ReportFiles:
    """Paths written by :func:`write_report` (figures None when not drawn)."""

    json: Path
    markdown: Path
    gap_map: Path | None
    residual_spectrum: Path | None


def _phase_rms(gap: Any) -> dict[str, float | None] | None:
    stats = _gap_stats(gap)
    if stats is None:
        return None
    phase = stats.get("partitions", {}).get("phase")
    if not isinstance(phase, Mapping):
        return None
    return {k: _num(v.get("rms_m")) for k, v in phase.items()}


def write_report(
    report: Mapping[str, Any],
    out_dir: str | Path,
    *,
    gap_experiments: Sequence[Mapping[str, Any]] | None = None,
    title: str = "Sim-to-real gap diagnosis",
    figures: bool = True,
) -> ReportFiles:
    """Write ``report.json``, ``report.md`` and (with matplotlib) the figures.

    Parameters
    ----------
    report : mapping
        See the module docstring.
    out_dir : str or Path
        Output directory (created).
    gap_experiments : sequence of mapping, optional
        Arrays for the gap map (see :func:`plot_gap_map`); without them no gap map.
    title : str
        Report title.
    figures : bool
        Draw figures (skipped silently when matplotlib is missing).

    Returns
    -------
    ReportFiles
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    before, after = report.get("gap_before"), report.get("gap_after")
    gap_map = spectrum = None
    if figures:
        try:
            import matplotlib  # noqa: F401
        except ImportError:  # pragma: no cover - exercised only without the extra
            figures = False
    if figures and gap_experiments:
        gap_map = out / FIGURE_NAMES["gap_map"]
        plot_gap_map(
            gap_experiments,
            gap_map,
            segment_rms_before_m=_phase_rms(before),
            segment_rms_after_m=_phase_rms(after),
            title=title,
        )
    if figures and isinstance(before, Mapping) and before.get("time_spectrum"):
        spectrum = out / FIGURE_NAMES["residual_spectrum"]
        a = after if isinstance(after, Mapping) else {}
        plot_residual_spectrum(
            before.get("time_spectrum"),
            before.get("spatial_spectrum"),
            spectrum,
            lead_m=_num(before.get("lead_m")),
            time_spectrum_after=a.get("time_spectrum"),
            spatial_spectrum_after=a.get("spatial_spectrum"),
            title=title,
        )
    links = {}
    if gap_map is not None:
        links["Gap map"] = gap_map.name
    if spectrum is not None:
        links["Residual spectrum"] = spectrum.name
    json_path = write_json(report, out / JSON_NAME)
    md_path = out / MARKDOWN_NAME
    md_path.write_text(markdown_report(report, title=title, figures=links), encoding="utf-8")
    return ReportFiles(
        json=json_path, markdown=md_path, gap_map=gap_map, residual_spectrum=spectrum
    )
