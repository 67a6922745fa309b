"""Independent integer reference model of the FPGA PID controller (docs/controller.md).

This module is the test oracle the Rust core is compared against bit for bit. It is
written from the specification only, with Python's arbitrary-precision integers: no
numpy and no floating point anywhere in the datapath. Floats appear only on the host
side, in :func:`quantize_float`, which converts them exactly through
:class:`fractions.Fraction`.

A fixed-point format is a dict::

    {"signed": bool, "word_bits": int, "int_bits": int,
     "rounding": "truncate" | "half_up" | "half_even",
     "overflow": "saturate" | "wrap"}

and a value in it is ``raw * 2**-frac_bits`` with ``frac_bits = word_bits - int_bits``.

Resolutions of points the specification leaves open (kept in sync with the Rust side):

* Requantisation rounds first, then applies the overflow mode; the overflow flag is set
  when the rounded raw value lies outside the raw range (for saturate and wrap alike).
  Rounding to zero (underflow) is never flagged.
* ``e = r - y`` uses the requantised ``y`` (measurement_format), aligned exactly with the
  integer ``r`` (0 fraction bits) to ``max(0, f_meas)`` fraction bits.
  ``dy = y - y_prev`` is the exact difference of two requantised measurements (a wrapped
  counter therefore gives a large jump unless error_format wraps it back).
* ``inc = ki * e`` is exact (``f_gain + f_error`` fraction bits); the candidate integrator
  is ``requant(acc + inc)`` with ``acc`` and ``inc`` aligned exactly to the larger of the
  two fraction-bit counts. ``i_overflow`` reports that requantisation, even when the
  conditional anti-windup then discards the candidate.
* anti_windup ``clamp``: ``out_min``/``out_max`` (raw in output_format) are converted to
  the integrator's fraction bits. When that conversion is inexact they are rounded
  *inward*, ``out_max`` down (floor) and ``out_min`` up (ceil); with an integer-valued
  candidate this makes "clamp to the converted bound" identical to an exact value
  comparison with the original bound. For the usual range ``out_min <= 0 <= out_max``
  inward rounding is rounding toward zero. The converted bounds are then limited to the
  integrator's raw range (a bound outside that range can never be reached by a candidate,
  and this keeps ``acc`` a valid raw value). ``integrator_held`` is True when the
  candidate lay strictly outside the converted bounds (i.e. the clamp changed it).
* anti_windup ``conditional``: the test uses the *exact* sum ``P + acc' + D`` (aligned to
  the largest fraction-bit count, not requantised to output_format) compared exactly with
  ``out_min``/``out_max``; "outside" is strict (``>`` max or ``<`` min) and the sign of
  ``inc`` is the sign of the exact product ``ki * e``. When frozen, ``acc`` keeps its
  previous value and ``integrator_held`` is True (even if the candidate happened to equal
  it).
* ``u = requant(P + acc + D, output_format)`` (exact three-term sum), then clamped to
  ``[out_min, out_max]`` in output_format raw units; ``u_saturated`` is True only when the
  requantised value was strictly outside the range. ``code`` uses the clamped ``u``.
* The state ``u_prev_saturation`` named in the spec plays no role in the listed
  equations and is not modelled.
* Host-side constants: gains, ``output_min``/``output_max`` and ``dac_scale`` are quantised
  with :func:`quantize_float` (round half to even of the exact value, ValueError if the
  *rounded* raw value is outside the raw range). ``dac_scale`` is the IEEE-754 double
  quotient ``output_unit_v / dac_lsb_v`` (one correctly rounded float division), then
  quantised exactly. ``out_min > out_max`` after quantisation is rejected (ValueError).
"""

from __future__ import annotations

import math
import operator
from fractions import Fraction

ROUNDING_MODES = ("truncate", "half_up", "half_even")
OVERFLOW_MODES = ("saturate", "wrap")
ANTI_WINDUP_MODES = ("none", "clamp", "conditional")

FORMAT_KEYS = (
    "gain_format",
    "measurement_format",
    "error_format",
    "term_format",
    "integrator_format",
    "output_format",
    "dac_format",
    "dac_scale_format",
)

STEP_KEYS = (
    "e",
    "p",
    "i",
    "d",
    "u",
    "code",
    "e_overflow",
    "p_overflow",
    "d_overflow",
    "i_overflow",
    "u_overflow",
    "u_saturated",
    "dac_overflow",
    "integrator_held",
    "e_frac",
    "p_frac",
    "i_frac",
    "d_frac",
    "u_frac",
    "code_frac",
    # extras (not required by the Rust comparison, useful when debugging)
    "y",
    "y_frac",
    "y_overflow",
    "dy",
    "dy_overflow",
)


# --------------------------------------------------------------------------- formats


def validate_format(fmt: dict) -> None:
    """Raise ValueError unless ``fmt`` is a valid format (docs/controller.md limits)."""
    signed = fmt["signed"]
    if not isinstance(signed, bool):
        raise TypeError(f"signed must be a bool, got {signed!r}")
    word = operator.index(fmt["word_bits"])
    int_bits = operator.index(fmt["int_bits"])
    max_word = 64 if signed else 63
    if not 1 <= word <= max_word:
        raise ValueError(f"word_bits must be in [1, {max_word}], got {word}")
    frac = word - int_bits
    if not -64 <= frac <= 64:
        raise ValueError(f"frac_bits must be in [-64, 64], got {frac}")
    if fmt["rounding"] not in ROUNDING_MODES:
        raise ValueError(f"unknown rounding mode {fmt['rounding']!r}")
    if fmt["overflow"] not in OVERFLOW_MODES:
        raise ValueError(f"unknown overflow mode {fmt['overflow']!r}")


def frac_bits(fmt: dict) -> int:
    """Number of fraction bits: ``word_bits - int_bits`` (may be negative)."""
    return operator.index(fmt["word_bits"]) - operator.index(fmt["int_bits"])


def raw_range(fmt: dict) -> tuple[int, int]:
    """Inclusive raw range ``(lo, hi)`` of the format."""
    word = operator.index(fmt["word_bits"])
    if fmt["signed"]:
        return -(1 << (word - 1)), (1 << (word - 1)) - 1
    return 0, (1 << word) - 1


def _round_shift(raw: int, s: int, mode: str) -> int:
    """Exact ``raw / 2**s`` (s > 0) rounded to an integer with ``mode``."""
    q = raw >> s  # floor, also for negative raw
    if mode == "truncate":
        return q
    rem = raw - (q << s)  # 0 <= rem < 2**s
    half = 1 << (s - 1)
    if mode == "half_up":
        return q + 1 if rem >= half else q
    if mode == "half_even":
        if rem > half:
            return q + 1
        if rem == half:
            return q + (q & 1)
        return q
    raise ValueError(f"unknown rounding mode {mode!r}")


def requantize(raw: int, frac_in: int, fmt: dict) -> tuple[int, bool]:
    """Requantise the exact value ``raw * 2**-frac_in`` into ``fmt``.

    Returns ``(raw_out, overflow)``. Rounding (when bits are dropped) comes first, then the
    overflow handling; the flag is set for both saturate and wrap.
    """
    validate_format(fmt)
    raw = operator.index(raw)
    frac_in = operator.index(frac_in)
    f = frac_bits(fmt)
    if f >= frac_in:
        out = raw << (f - frac_in)
    else:
        out = _round_shift(raw, frac_in - f, fmt["rounding"])
    lo, hi = raw_range(fmt)
    if lo <= out <= hi:
        return out, False
    if fmt["overflow"] == "saturate":
        return (lo if out < lo else hi), True
    word = operator.index(fmt["word_bits"])
    mask = (1 << word) - 1
    if fmt["signed"]:
        half = 1 << (word - 1)
        return ((out + half) & mask) - half, True
    return out & mask, True


def quantize_float(value: float, fmt: dict) -> int:
    """Host-side conversion of a real number into a raw value of ``fmt``.

    ``round_half_even(value * 2**frac_bits)`` computed exactly with Fraction; ValueError if
    the value is not finite or the rounded raw value is outside the raw range.
    """
    validate_format(fmt)
    if isinstance(value, float) and not math.isfinite(value):
        raise ValueError(f"cannot quantise non-finite value {value!r}")
    exact = Fraction(value) * Fraction(2) ** frac_bits(fmt)
    raw = round(exact)  # Fraction.__round__ rounds half to even
    lo, hi = raw_range(fmt)
    if not lo <= raw <= hi:
        raise ValueError(f"{value!r} is outside the range of {fmt!r} (raw {raw})")
    return raw


def _shift_to(raw: int, f_from: int, f_to: int) -> int:
    """Exact alignment: ``raw`` with ``f_from`` fraction bits expressed with ``f_to >= f_from``."""
    assert f_to >= f_from
    return raw << (f_to - f_from)


def exact_sum(*terms: tuple[int, int]) -> tuple[int, int]:
    """Exact sum of ``(raw, frac)`` terms, aligned to the largest fraction-bit count."""
    f = max(fr for _, fr in terms)
    return sum(_shift_to(r, fr, f) for r, fr in terms), f


def compare(a: tuple[int, int], b: tuple[int, int]) -> int:
    """Exact comparison of two ``(raw, frac)`` values: -1, 0 or 1."""
    f = max(a[1], b[1])
    x = _shift_to(a[0], a[1], f)
    y = _shift_to(b[0], b[1], f)
    return (x > y) - (x < y)


def _floor_shift(raw: int, s: int) -> int:
    return raw >> s


def _ceil_shift(raw: int, s: int) -> int:
    return -((-raw) >> s)


# --------------------------------------------------------------------------- controller


class ReferencePid:
    """Bit-exact reference of one PID channel (see the module docstring for resolutions).

    Public attributes after construction (raw integers): ``kp``, ``ki``, ``kd`` (in
    gain_format), ``out_min``, ``out_max`` (in output_format), ``dac_scale`` (in
    dac_scale_format), ``acc_min``, ``acc_max`` (the clamp anti-windup bounds in
    integrator_format: out_min rounded up, out_max rounded down, i.e. toward zero for
    ranges containing 0, then limited to the integrator's raw range).
    """

    def __init__(self, cfg: dict):
        self.fmt = {}
        for key in FORMAT_KEYS:
            fmt = dict(cfg[key])
            validate_format(fmt)
            self.fmt[key] = fmt
        f = {key: frac_bits(fmt) for key, fmt in self.fmt.items()}
        self.f_gain = f["gain_format"]
        self.f_meas = f["measurement_format"]
        self.f_err = f["error_format"]
        self.f_term = f["term_format"]
        self.f_int = f["integrator_format"]
        self.f_out = f["output_format"]
        self.f_dac = f["dac_format"]
        self.f_scale = f["dac_scale_format"]

        self.anti_windup = cfg["anti_windup"]
        if self.anti_windup not in ANTI_WINDUP_MODES:
            raise ValueError(f"unknown anti_windup mode {self.anti_windup!r}")

        gain_fmt = self.fmt["gain_format"]
        self.kp = quantize_float(cfg["kp"], gain_fmt)
        self.ki = quantize_float(cfg["ki"], gain_fmt)
        self.kd = quantize_float(cfg["kd"], gain_fmt)

        out_fmt = self.fmt["output_format"]
        self.out_min = quantize_float(cfg["output_min"], out_fmt)
        self.out_max = quantize_float(cfg["output_max"], out_fmt)
        if self.out_min > self.out_max:
            raise ValueError("output_min > output_max after quantisation")

        scale = float(cfg["output_unit_v"]) / float(cfg["dac_lsb_v"])
        self.dac_scale = quantize_float(scale, self.fmt["dac_scale_format"])

        # Clamp anti-windup bounds in integrator_format (inward rounding, see docstring).
        if self.f_int >= self.f_out:
            acc_min = _shift_to(self.out_min, self.f_out, self.f_int)
            acc_max = _shift_to(self.out_max, self.f_out, self.f_int)
        else:
            s = self.f_out - self.f_int
            acc_min = _ceil_shift(self.out_min, s)
            acc_max = _floor_shift(self.out_max, s)
        ilo, ihi = raw_range(self.fmt["integrator_format"])
        self.acc_min = min(max(acc_min, ilo), ihi)
        self.acc_max = min(max(acc_max, ilo), ihi)
        if self.anti_windup == "clamp" and self.acc_min > self.acc_max:
            raise ValueError("no integrator value lies in [output_min, output_max]")

        self.reset()

    def reset(self) -> None:
        self.acc = 0
        self.y_prev = None

    def _rq(self, raw: int, frac_in: int, key: str) -> tuple[int, bool]:
        return requantize(raw, frac_in, self.fmt[key])

    def step(self, r_counts: int, y_counts: int) -> dict:
        r = operator.index(r_counts)
        y_in = operator.index(y_counts)

        # y = requant(y[n], measurement_format)
        y, y_ovf = self._rq(y_in, 0, "measurement_format")
        if self.y_prev is None:
            self.y_prev = y

        # e = requant(r - y, error_format): exact difference, r has 0 fraction bits
        diff, f_diff = exact_sum((r, 0), (-y, self.f_meas))
        e, e_ovf = self._rq(diff, f_diff, "error_format")

        # dy = requant(y - y_prev, error_format)
        dy, dy_ovf = self._rq(y - self.y_prev, self.f_meas, "error_format")

        f_prod = self.f_gain + self.f_err
        # P = requant(kp * e, term_format)
        p, p_ovf = self._rq(self.kp * e, f_prod, "term_format")
        # D = requant(-(kd * dy), term_format)
        d, d_ovf = self._rq(-(self.kd * dy), f_prod, "term_format")

        # inc = ki * e (exact); acc' = requant(acc + inc, integrator_format)
        inc = self.ki * e
        s_raw, s_frac = exact_sum((self.acc, self.f_int), (inc, f_prod))
        cand, i_ovf = self._rq(s_raw, s_frac, "integrator_format")

        lo_val = (self.out_min, self.f_out)
        hi_val = (self.out_max, self.f_out)
        held = False
        if self.anti_windup == "none":
            acc = cand
        elif self.anti_windup == "clamp":
            acc = min(max(cand, self.acc_min), self.acc_max)
            held = acc != cand
        else:  # conditional
            total = exact_sum((p, self.f_term), (cand, self.f_int), (d, self.f_term))
            above = compare(total, hi_val) > 0
            below = compare(total, lo_val) < 0
            held = (above and inc > 0) or (below and inc < 0)
            acc = self.acc if held else cand
        self.acc = acc

        # u = requant(P + acc + D, output_format), then clamp to the output range
        u_raw, u_frac_in = exact_sum((p, self.f_term), (acc, self.f_int), (d, self.f_term))
        u, u_ovf = self._rq(u_raw, u_frac_in, "output_format")
        u_sat = u < self.out_min or u > self.out_max
        u = min(max(u, self.out_min), self.out_max)

        # code = requant(u * dac_scale, dac_format)
        code, dac_ovf = self._rq(u * self.dac_scale, self.f_out + self.f_scale, "dac_format")

        self.y_prev = y
        return {
            "e": e,
            "p": p,
            "i": acc,
            "d": d,
            "u": u,
            "code": code,
            "e_overflow": e_ovf,
            "p_overflow": p_ovf,
            "d_overflow": d_ovf,
            "i_overflow": i_ovf,
            "u_overflow": u_ovf,
            "u_saturated": u_sat,
            "dac_overflow": dac_ovf,
            "integrator_held": held,
            "e_frac": self.f_err,
            "p_frac": self.f_term,
            "i_frac": self.f_int,
            "d_frac": self.f_term,
            "u_frac": self.f_out,
            "code_frac": self.f_dac,
            "y": y,
            "y_frac": self.f_meas,
            "y_overflow": y_ovf,
            "dy": dy,
            "dy_overflow": dy_ovf,
        }


def run(cfg: dict, reference_counts: list[int], measured_counts: list[int]) -> dict[str, list]:
    """Reset a fresh controller and step through the sequences; one list per key."""
    if len(reference_counts) != len(measured_counts):
        raise ValueError("reference_counts and measured_counts differ in length")
    pid = ReferencePid(cfg)
    out: dict[str, list] = {key: [] for key in STEP_KEYS}
    for r, y in zip(reference_counts, measured_counts, strict=True):
        res = pid.step(r, y)
        for key in STEP_KEYS:
            out[key].append(res[key])
    return out
