"""Self-checks of the plain-Python PID reference (tests/pid_reference.py).

Every expected value below is computed by hand in the comments. These tests do not
import nanostage: they validate the oracle itself, before it is used against Rust.
"""

from __future__ import annotations

import sys
from fractions import Fraction
from math import floor
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

sys.path.insert(0, str(Path(__file__).resolve().parent))

from pid_reference import (
    ReferencePid,
    frac_bits,
    quantize_float,
    raw_range,
    requantize,
    run,
    validate_format,
)


def fmt(signed=True, word=16, int_bits=16, rounding="half_even", overflow="saturate"):
    return {
        "signed": signed,
        "word_bits": word,
        "int_bits": int_bits,
        "rounding": rounding,
        "overflow": overflow,
    }


I32 = fmt(True, 32, 32)
I16 = fmt(True, 16, 16)


# --------------------------------------------------------------------------- formats


def test_frac_bits_and_range():
    assert frac_bits(fmt(True, 16, 8)) == 8
    assert frac_bits(fmt(True, 16, 20)) == -4
    assert raw_range(fmt(True, 16, 8)) == (-32768, 32767)
    assert raw_range(fmt(False, 8, 4)) == (0, 255)  # NI <+,8,4>: 0 .. 15.9375, delta 1/16
    assert raw_range(fmt(True, 64, 0)) == (-(2**63), 2**63 - 1)


@pytest.mark.parametrize(
    "bad",
    [
        fmt(True, 0, 0),
        fmt(True, 65, 65),
        fmt(False, 64, 64),  # unsigned is limited to 63 bits
        fmt(True, 16, -49),  # frac 65
        fmt(True, 16, 81),  # frac -65
        fmt(rounding="nearest"),
        fmt(overflow="clip"),
    ],
)
def test_invalid_formats(bad):
    with pytest.raises(ValueError):
        validate_format(bad)


def test_extreme_valid_formats():
    validate_format(fmt(True, 64, 0))
    validate_format(fmt(False, 63, 63))
    validate_format(fmt(True, 1, -63))  # frac 64
    validate_format(fmt(True, 1, 65))  # frac -64


# --------------------------------------------------------------------------- rounding

# All cases drop s = 2 bits (frac_in = 2 -> frac 0), so raw/4 is the exact value:
#   raw  6 ->  1.5 (tie)    raw -6 -> -1.5 (tie)    raw 10 -> 2.5 (tie)   raw -10 -> -2.5
#   raw  5 ->  1.25         raw -5 -> -1.25         raw  7 -> 1.75        raw  -7 -> -1.75
ROUNDING_CASES = {
    # truncate = floor
    "truncate": {6: 1, -6: -2, 10: 2, -10: -3, 5: 1, -5: -2, 7: 1, -7: -2},
    # half_up = floor(x + 0.5): 1.5->2, -1.5->-1, 2.5->3, -2.5->-2, 1.25->1, -1.25->-1,
    # 1.75->2, -1.75->-2
    "half_up": {6: 2, -6: -1, 10: 3, -10: -2, 5: 1, -5: -1, 7: 2, -7: -2},
    # half_even: ties to even: 1.5->2, -1.5->-2, 2.5->2, -2.5->-2; others nearest
    "half_even": {6: 2, -6: -2, 10: 2, -10: -2, 5: 1, -5: -1, 7: 2, -7: -2},
}


@pytest.mark.parametrize("mode", sorted(ROUNDING_CASES))
def test_rounding_modes_s2(mode):
    for raw, expected in ROUNDING_CASES[mode].items():
        assert requantize(raw, 2, fmt(rounding=mode)) == (expected, False), (mode, raw)


@pytest.mark.parametrize(
    "mode, expected",
    [
        # one bit dropped: 0.5, -0.5, 1.5, -1.5, 3.5
        ("truncate", [0, -1, 1, -2, 3]),  # floor
        ("half_up", [1, 0, 2, -1, 4]),  # floor(x + 0.5)
        ("half_even", [0, 0, 2, -2, 4]),  # even neighbour
    ],
)
def test_rounding_modes_s1_ties(mode, expected):
    raws = [1, -1, 3, -3, 7]
    got = [requantize(r, 1, fmt(rounding=mode))[0] for r in raws]
    assert got == expected


def test_rounding_large_shift_and_sticky_bits():
    # raw = 2**40 + 2**39 + 1 with 40 fraction bits = 1.5 + 2**-40: above the tie
    raw = 2**40 + 2**39 + 1
    assert requantize(raw, 40, fmt(rounding="half_even"))[0] == 2
    assert requantize(raw, 40, fmt(rounding="truncate"))[0] == 1
    # -(2**40 + 2**39) / 2**40 = -1.5 exactly: half_even -2, half_up -1, truncate -2
    raw = -(2**40 + 2**39)
    assert requantize(raw, 40, fmt(rounding="half_even"))[0] == -2
    assert requantize(raw, 40, fmt(rounding="half_up"))[0] == -1
    assert requantize(raw, 40, fmt(rounding="truncate"))[0] == -2
    # -(2**40 + 2**39 - 1) / 2**40 = -1.5 + 2**-40: nearest is -1 for both round modes
    raw = -(2**40 + 2**39 - 1)
    assert requantize(raw, 40, fmt(rounding="half_even"))[0] == -1
    assert requantize(raw, 40, fmt(rounding="half_up"))[0] == -1
    assert requantize(raw, 40, fmt(rounding="truncate"))[0] == -2


def test_left_shift_is_exact():
    # 3 (frac 0) into frac 4: 3 * 16 = 48
    assert requantize(3, 0, fmt(True, 16, 12)) == (48, False)
    # -5 with frac 1 (-2.5) into frac 3: -5 * 4 = -20 (= -2.5 * 8)
    assert requantize(-5, 1, fmt(True, 16, 13)) == (-20, False)
    # negative frac_in: raw 3 with frac_in -2 is 12; into frac 0 -> 12
    assert requantize(3, -2, I16) == (12, False)


def test_negative_frac_format():
    # word 16, int 20 -> frac -4: LSB = 16. 40 -> 40/16 = 2.5
    f = fmt(True, 16, 20)
    assert requantize(40, 0, dict(f, rounding="half_even")) == (2, False)
    assert requantize(40, 0, dict(f, rounding="half_up")) == (3, False)
    assert requantize(40, 0, dict(f, rounding="truncate")) == (2, False)
    # 56 / 16 = 3.5 -> half_even 4
    assert requantize(56, 0, f) == (4, False)
    # -40 / 16 = -2.5 -> half_even -2, half_up -2, truncate -3
    assert requantize(-40, 0, dict(f, rounding="half_even")) == (-2, False)
    assert requantize(-40, 0, dict(f, rounding="half_up")) == (-2, False)
    assert requantize(-40, 0, dict(f, rounding="truncate")) == (-3, False)


def test_underflow_is_not_flagged():
    # 1 * 2**-4 = 0.0625 -> rounds to 0 without overflow
    assert requantize(1, 4, I16) == (0, False)
    assert requantize(-1, 4, I16) == (0, False)  # -0.0625 -> 0 (half_even)
    assert requantize(-1, 4, fmt(rounding="truncate")) == (-1, False)  # floor


# --------------------------------------------------------------------------- overflow


def test_signed_saturate_and_wrap():
    sat = fmt(True, 8, 8, overflow="saturate")
    wrap = fmt(True, 8, 8, overflow="wrap")
    # range [-128, 127]
    assert requantize(127, 0, sat) == (127, False)
    assert requantize(-128, 0, sat) == (-128, False)
    assert requantize(128, 0, sat) == (127, True)
    assert requantize(200, 0, sat) == (127, True)
    assert requantize(-129, 0, sat) == (-128, True)
    assert requantize(-200, 0, sat) == (-128, True)
    # wrap: keep the low 8 bits, two's complement
    assert requantize(127, 0, wrap) == (127, False)
    assert requantize(128, 0, wrap) == (-128, True)  # 128 - 256
    assert requantize(200, 0, wrap) == (-56, True)  # 200 - 256
    assert requantize(300, 0, wrap) == (44, True)  # 300 - 256
    assert requantize(-129, 0, wrap) == (127, True)  # -129 + 256
    assert requantize(-200, 0, wrap) == (56, True)  # -200 + 256
    assert requantize(-1000, 0, wrap) == (24, True)  # -1000 + 4*256


def test_unsigned_saturate_and_wrap():
    sat = fmt(False, 8, 8, overflow="saturate")
    wrap = fmt(False, 8, 8, overflow="wrap")
    # range [0, 255]
    assert requantize(255, 0, sat) == (255, False)
    assert requantize(256, 0, sat) == (255, True)
    assert requantize(-1, 0, sat) == (0, True)
    assert requantize(256, 0, wrap) == (0, True)
    assert requantize(300, 0, wrap) == (44, True)  # 300 - 256
    assert requantize(-1, 0, wrap) == (255, True)  # -1 + 256
    assert requantize(-200, 0, wrap) == (56, True)  # -200 + 256


def test_overflow_after_rounding():
    # 255 with 1 fraction bit = 127.5; half_even -> 128 (even) -> overflows I8
    assert requantize(255, 1, fmt(True, 8, 8, "half_even", "saturate")) == (127, True)
    assert requantize(255, 1, fmt(True, 8, 8, "half_even", "wrap")) == (-128, True)
    # truncate -> 127, fits
    assert requantize(255, 1, fmt(True, 8, 8, "truncate", "saturate")) == (127, False)
    # 253 / 2 = 126.5 -> half_even 126, half_up 127: both fit
    assert requantize(253, 1, fmt(True, 8, 8, "half_even")) == (126, False)
    assert requantize(253, 1, fmt(True, 8, 8, "half_up")) == (127, False)


def test_word_64_wrap():
    w64 = fmt(True, 64, 64, overflow="wrap")
    assert requantize(2**63, 0, w64) == (-(2**63), True)
    assert requantize(2**64 + 5, 0, w64) == (5, True)
    u63 = fmt(False, 63, 63, overflow="wrap")
    assert requantize(2**63 + 7, 0, u63) == (7, True)


# Independent formulation with Fraction, floor and modular arithmetic.
def _oracle(raw, frac_in, f):
    x = Fraction(raw) * Fraction(2) ** (frac_bits(f) - frac_in)
    if f["rounding"] == "truncate":
        q = floor(x)
    elif f["rounding"] == "half_up":
        q = floor(x + Fraction(1, 2))
    else:
        q = round(x)  # Fraction: ties to even
    lo, hi = raw_range(f)
    if lo <= q <= hi:
        return q, False
    if f["overflow"] == "saturate":
        return min(max(q, lo), hi), True
    return (q - lo) % 2 ** f["word_bits"] + lo, True


@st.composite
def formats(draw):
    signed = draw(st.booleans())
    word = draw(st.integers(1, 64 if signed else 63))
    frac = draw(st.integers(-64, 64))
    return fmt(
        signed,
        word,
        word - frac,
        draw(st.sampled_from(["truncate", "half_up", "half_even"])),
        draw(st.sampled_from(["saturate", "wrap"])),
    )


@settings(max_examples=3000, deadline=None)
@given(
    raw=st.one_of(st.integers(-(2**140), 2**140), st.integers(-300, 300)),
    frac_in=st.integers(-70, 140),
    f=formats(),
)
def test_requantize_matches_fraction_oracle(raw, frac_in, f):
    assert requantize(raw, frac_in, f) == _oracle(raw, frac_in, f)


# --------------------------------------------------------------------------- quantize_float


def test_quantize_float():
    q88 = fmt(True, 16, 8)  # Q8.8, LSB 1/256
    assert quantize_float(1.5, q88) == 384  # 1.5 * 256
    assert quantize_float(0.1, q88) == 26  # 25.6000000000000014 -> 26
    assert quantize_float(2.0**-9, q88) == 0  # 0.5 LSB: tie -> 0 (even)
    assert quantize_float(3 * 2.0**-9, q88) == 2  # 1.5 LSB: tie -> 2
    assert quantize_float(-(2.0**-9), q88) == 0  # -0.5 -> 0
    assert quantize_float(-3 * 2.0**-9, q88) == -2  # -1.5 -> -2
    assert quantize_float(5 * 2.0**-9, q88) == 2  # 2.5 -> 2
    assert quantize_float(32767 / 256, q88) == 32767  # max
    assert quantize_float(-128.0, q88) == -32768  # min
    # -32768.5 LSB: tie, even neighbour is -32768 (in range)
    assert quantize_float(-32768.5 / 256, q88) == -32768
    with pytest.raises(ValueError):
        quantize_float(32767.5 / 256, q88)  # tie -> 32768 (even) -> out of range
    with pytest.raises(ValueError):
        quantize_float(-32769 / 256, q88)
    with pytest.raises(ValueError):
        quantize_float(float("nan"), q88)
    with pytest.raises(ValueError):
        quantize_float(float("inf"), q88)
    # range is checked after rounding: -0.001 in unsigned Q.8 is -0.256 LSB -> 0
    assert quantize_float(-0.001, fmt(False, 16, 8)) == 0
    with pytest.raises(ValueError):
        quantize_float(-0.003, fmt(False, 16, 8))  # -0.768 LSB -> -1
    # negative frac (-4): 40 -> 2.5 -> 2; 56 -> 3.5 -> 4
    assert quantize_float(40.0, fmt(True, 8, 12)) == 2
    assert quantize_float(56.0, fmt(True, 8, 12)) == 4
    assert quantize_float(450.0, I16) == 450


# --------------------------------------------------------------------------- PID helpers


def make_cfg(**over):
    cfg = {
        "kp": 450.0,
        "ki": 2.0,
        "kd": 40.0,
        "gain_format": I16,
        "measurement_format": I32,
        "error_format": I32,
        "term_format": I32,
        "integrator_format": I32,
        "output_format": I16,
        "dac_format": I16,
        "dac_scale_format": fmt(False, 16, 8),  # unsigned, 8 fraction bits
        "output_min": -10000.0,
        "output_max": 10000.0,
        "anti_windup": "none",
        "output_unit_v": 1.0,
        "dac_lsb_v": 2.0,  # dac_scale = 0.5 -> raw 128 (frac 8)
        "clock_hz": 40e6,
        "ticks_per_sample": 40000,
        "latency_ticks": 1,
    }
    cfg.update(over)
    return cfg


# --------------------------------------------------------------------------- integer PID


def test_integer_pid_sequence_by_hand():
    # kp=450, ki=2, kd=40, every datapath format an integer (frac 0), output I16
    # saturating, range +-10000, dac_scale = 0.5 (raw 128, frac 8), code = u * 128 / 256.
    #
    # n  r    y   e   dy   P=450e   D=-40dy  inc=2e  acc   u=P+acc+D         code
    # 0  0    0   0   0    0        0        0       0     0                 0
    # 1  10   0   10  0    4500     0        20      20    4520              2260
    # 2  10   2   8   2    3600     -80      16      36    3556              1778
    # 3  10   5   5   3    2250     -120     10      46    2176              1088
    # 4  10   9   1   4    450      -160     2       48    338               169
    # 5  100  9   91  0    40950    0        182     230   41180 -> I16 sat  10000*0.5
    #                                                      32767 (u_overflow),
    #                                                      clamp 10000 (u_saturated)
    # 6  10   12  -2  3    -900     -120     -4      226   -794              -397
    pid = ReferencePid(make_cfg())
    assert (pid.kp, pid.ki, pid.kd, pid.dac_scale) == (450, 2, 40, 128)
    assert (pid.out_min, pid.out_max) == (-10000, 10000)
    r = [0, 10, 10, 10, 10, 100, 10]
    y = [0, 0, 2, 5, 9, 9, 12]
    out = run(make_cfg(), r, y)
    assert out["e"] == [0, 10, 8, 5, 1, 91, -2]
    assert out["dy"] == [0, 0, 2, 3, 4, 0, 3]
    assert out["p"] == [0, 4500, 3600, 2250, 450, 40950, -900]
    assert out["d"] == [0, 0, -80, -120, -160, 0, -120]
    assert out["i"] == [0, 20, 36, 46, 48, 230, 226]
    assert out["u"] == [0, 4520, 3556, 2176, 338, 10000, -794]
    assert out["code"] == [0, 2260, 1778, 1088, 169, 5000, -397]
    assert out["u_overflow"] == [False] * 5 + [True, False]
    assert out["u_saturated"] == [False] * 5 + [True, False]
    for key in ("e_overflow", "p_overflow", "d_overflow", "i_overflow", "dac_overflow"):
        assert out[key] == [False] * 7, key
    assert out["integrator_held"] == [False] * 7
    for key in ("e_frac", "p_frac", "i_frac", "d_frac", "u_frac", "code_frac"):
        assert out[key] == [0] * 7, key


def test_integer_pid_overflow_flags():
    # error I8 saturate, term I16 saturate, dac I8 saturate, integrator I8 wrap.
    # n=0: y=0 -> y_prev=0; r=200: e = 200 -> I8 sat 127 (e_overflow)
    #   P = 450*127 = 57150 -> I16 sat 32767 (p_overflow)
    #   inc = 2*127 = 254; acc' = 254 -> I8 wrap 254-256 = -2 (i_overflow)
    #   D = 0; u = 32767 - 2 = 32765 -> I16 fits; clamp 10000 (u_saturated)
    #   code = 10000*0.5 = 5000 -> I8 sat 127 (dac_overflow)
    # n=1: r=0, y=-1: e = 1, dy = -1 - 0 = -1, D = -(40*-1) = 40
    #   P = 450; inc = 2; acc' = -2 + 2 = 0; u = 450 + 0 + 40 = 490; code 245 -> I8 sat 127
    cfg = make_cfg(
        error_format=fmt(True, 8, 8),
        term_format=I16,
        integrator_format=fmt(True, 8, 8, overflow="wrap"),
        dac_format=fmt(True, 8, 8),
    )
    out = run(cfg, [200, 0], [0, -1])
    assert out["e"] == [127, 1]
    assert out["e_overflow"] == [True, False]
    assert out["p"] == [32767, 450]
    assert out["p_overflow"] == [True, False]
    assert out["i"] == [-2, 0]
    assert out["i_overflow"] == [True, False]
    assert out["d"] == [0, 40]
    assert out["u"] == [10000, 490]
    assert out["u_overflow"] == [False, False]
    assert out["u_saturated"] == [True, False]
    assert out["code"] == [127, 127]
    assert out["dac_overflow"] == [True, True]


def test_measurement_wrap():
    # measurement I16 wrap: y = 40000 -> 40000 - 65536 = -25536 (y_overflow)
    # e = r - y = 0 + 25536 = 25536; next y = 40001 -> -25535, dy = 1
    out = run(
        make_cfg(measurement_format=fmt(True, 16, 16, overflow="wrap")), [0, 0], [40000, 40001]
    )
    assert out["y"] == [-25536, -25535]
    assert out["y_overflow"] == [True, True]
    assert out["e"] == [25536, 25535]
    assert out["dy"] == [0, 1]


# --------------------------------------------------------------------------- fractional PID


def test_fractional_pid_sequence_by_hand():
    # gains Q8.8 (frac 8): kp = 1.5 -> 384, ki = 0.1 -> 25.6 -> 26, kd = 0.625 -> 160
    # y, e integers (frac 0); products have 8 fraction bits.
    # term: frac 2, half_even; integrator: frac 4, truncate; output: frac 0, half_up.
    # dac_scale = 0.001 / (20/65536) = 3.2768 -> *4096 = 13421.77 -> 13422 (frac 12)
    # code = u*13422 / 4096, half_even.
    #
    # n=0: r=0 y=0: everything 0.
    # n=1: r=7 y=0: e=7 dy=0
    #   P = 384*7 = 2688 (f8) / 64 = 42 (f2) exact.    D = 0
    #   inc = 26*7 = 182 (f8); acc' = 0 + 182/16 = 11.375 -> trunc 11 (f4)
    #   u = 42*4 + 11 = 179 (f4) = 11.1875 -> 11;  code = 147642/4096 = 36.05 -> 36
    # n=2: r=7 y=3: e=4 dy=3
    #   P = 1536/64 = 24 (f2).  D = -(160*3) = -480/64 = -7.5 -> half_even -8 (f2)
    #   acc' = 11*16 + 104 = 280 (f8) / 16 = 17.5 -> 17
    #   u = 96 + 17 - 32 = 81 (f4) = 5.0625 -> 5;  code = 67110/4096 = 16.38 -> 16
    # n=3: r=7 y=5: e=2 dy=2
    #   P = 768/64 = 12. D = -320/64 = -5.  acc' = 17*16 + 52 = 324 / 16 = 20.25 -> 20
    #   u = 48 + 20 - 20 = 48 (f4) = 3 -> 3;  code = 40266/4096 = 9.83 -> 10
    # n=4: r=7 y=6: e=1 dy=1
    #   P = 384/64 = 6. D = -160/64 = -2.5 -> half_even -2.  acc' = 320 + 26 = 346/16 -> 21
    #   u = 24 + 21 - 8 = 37 (f4) = 2.3125 -> 2;  code = 26844/4096 = 6.55 -> 7
    # n=5: r=7 y=8: e=-1 dy=2
    #   P = -384/64 = -6. D = -320/64 = -5.  acc' = 21*16 - 26 = 310/16 = 19.375 -> 19
    #   u = -24 + 19 - 20 = -25 (f4) = -1.5625 -> floor(-1.0625) = -2
    #   code = -26844/4096 = -6.55 -> -7
    cfg = make_cfg(
        kp=1.5,
        ki=0.1,
        kd=0.625,
        gain_format=fmt(True, 16, 8),
        error_format=I16,
        term_format=fmt(True, 32, 30, "half_even"),
        integrator_format=fmt(True, 32, 28, "truncate"),
        output_format=fmt(True, 16, 16, "half_up"),
        dac_format=fmt(True, 16, 16, "half_even"),
        dac_scale_format=fmt(False, 16, 4),
        output_min=-1000.0,
        output_max=1000.0,
        output_unit_v=1e-3,
        dac_lsb_v=20 / 65536,
    )
    pid = ReferencePid(cfg)
    assert (pid.kp, pid.ki, pid.kd, pid.dac_scale) == (384, 26, 160, 13422)
    out = run(cfg, [0, 7, 7, 7, 7, 7], [0, 0, 3, 5, 6, 8])
    assert out["e"] == [0, 7, 4, 2, 1, -1]
    assert out["p"] == [0, 42, 24, 12, 6, -6]
    assert out["d"] == [0, 0, -8, -5, -2, -5]
    assert out["i"] == [0, 11, 17, 20, 21, 19]
    assert out["u"] == [0, 11, 5, 3, 2, -2]
    assert out["code"] == [0, 36, 16, 10, 7, -7]
    assert out["p_frac"][0] == 2 and out["d_frac"][0] == 2
    assert out["i_frac"][0] == 4 and out["u_frac"][0] == 0 and out["code_frac"][0] == 0
    assert out["e_frac"][0] == 0
    assert not any(any(out[k]) for k in out if k.endswith("_overflow"))


# --------------------------------------------------------------------------- anti-windup


def _aw_cfg(mode, **over):
    # kp = ki = 1, kd = 0, integer formats, output range [-10, 10]
    base = {"kp": 1.0, "ki": 1.0, "kd": 0.0, "output_min": -10.0, "output_max": 10.0}
    return make_cfg(**{**base, "anti_windup": mode, **over})


AW_R = [8, 8, 8, 0, -3]
AW_Y = [0, 0, 0, 0, 0]  # e = r; P = e; inc = e; D = 0


def test_anti_windup_none():
    # acc: 8, 16, 24, 24, 21;  P+acc: 16, 24, 32, 24, 18 -> all clamp to 10
    out = run(_aw_cfg("none"), AW_R, AW_Y)
    assert out["i"] == [8, 16, 24, 24, 21]
    assert out["u"] == [10, 10, 10, 10, 10]
    assert out["u_saturated"] == [True] * 5
    assert out["integrator_held"] == [False] * 5
    assert out["code"] == [5, 5, 5, 5, 5]


def test_anti_windup_clamp():
    # n0: acc' = 8 (inside [-10, 10]) -> 8; u = 8+8 = 16 -> 10 (sat)
    # n1: acc' = 8+8 = 16 -> clamped 10 (held); u = 8+10 = 18 -> 10 (sat)
    # n2: acc' = 18 -> 10 (held); u = 18 -> 10 (sat)
    # n3: e=0: acc' = 10 (equal to the bound: not held); u = 10 (not saturated)
    # n4: e=-3: acc' = 7; u = -3 + 7 = 4
    out = run(_aw_cfg("clamp"), AW_R, AW_Y)
    assert out["i"] == [8, 10, 10, 10, 7]
    assert out["u"] == [10, 10, 10, 10, 4]
    assert out["u_saturated"] == [True, True, True, False, False]
    assert out["integrator_held"] == [False, True, True, False, False]


def test_anti_windup_conditional():
    # n0: acc' = 8, P + acc' + D = 16 > 10 and inc = 8 > 0 -> frozen, acc = 0; u = 8
    # n1, n2: same (acc stays 0); u = 8
    # n3: e=0: inc = 0 -> acc' = 0, sum 0 inside -> acc = 0; u = 0
    # n4: e=-3: acc' = -3, sum = -6 inside -> acc = -3; u = -3 - 3 = -6
    out = run(_aw_cfg("conditional"), AW_R, AW_Y)
    assert out["i"] == [0, 0, 0, 0, -3]
    assert out["u"] == [8, 8, 8, 0, -6]
    assert out["u_saturated"] == [False] * 5
    assert out["integrator_held"] == [True, True, True, False, False]


def test_anti_windup_conditional_direction():
    # kd = 10. r = 0, y = [10, 5]
    # n0: y_prev = 10, e = -10, dy = 0, P = -10, D = 0, inc = -10, acc' = -10
    #     sum = -20 < -10 and inc < 0 -> frozen, acc = 0; u = -10 (== min, not saturated)
    # n1: e = -5, dy = -5, P = -5, D = -(10 * -5) = 50, inc = -5, acc' = -5
    #     sum = -5 - 5 + 50 = 40 > 10 but inc < 0 pulls back -> integrate, acc = -5
    #     u = 40 -> 10 (saturated)
    cfg = make_cfg(
        kp=1.0, ki=1.0, kd=10.0, output_min=-10.0, output_max=10.0, anti_windup="conditional"
    )
    out = run(cfg, [0, 0], [10, 5])
    assert out["d"] == [0, 50]
    assert out["i"] == [0, -5]
    assert out["integrator_held"] == [True, False]
    assert out["u"] == [-10, 10]
    assert out["u_saturated"] == [False, True]


def test_conditional_uses_exact_sum_not_requantised():
    # output frac 0 half_even, term frac 2, range [-10, 10], kp = 0.25 (Q8.8: 64), ki = 1, kd = 0
    # r = 2: e = 2, P = 64*2 = 128 (f8) -> 0.5 (f2 raw 2); inc = 512 (f8), acc' = 2 (f0 int)
    # Choose integrator frac 0 and initial r sequence so that acc' = 10 with P = 0.5:
    #   n0: e = 2 -> acc' = 2, sum = 2.5 inside -> acc = 2
    #   ...e = 2 each sample: acc = 2, 4, 6, 8, then n4: acc' = 10, sum = 10.5 > 10 with
    #   inc > 0 -> frozen at 8 (a requantised sum, half_even(10.5) = 10, would not freeze).
    #   u at n4 = 0.5 + 8 = 8.5 -> half_even 8.
    cfg = make_cfg(
        kp=0.25,
        ki=1.0,
        kd=0.0,
        gain_format=fmt(True, 16, 8),
        term_format=fmt(True, 32, 30),
        output_min=-10.0,
        output_max=10.0,
        anti_windup="conditional",
    )
    out = run(cfg, [2] * 5, [0] * 5)
    assert out["p"] == [2] * 5  # 0.5 with 2 fraction bits
    assert out["i"] == [2, 4, 6, 8, 8]
    assert out["integrator_held"] == [False] * 4 + [True]
    # u = half_even(P + acc): 2.5 -> 2, 4.5 -> 4, 6.5 -> 6, 8.5 -> 8, 8.5 -> 8
    assert out["u"] == [2, 4, 6, 8, 8]


def test_clamp_bounds_rounding():
    # output frac 2: out range +-2.75 (raw +-11); integrator frac 0:
    #   acc_max = floor(2.75) = 2, acc_min = ceil(-2.75) = -2 (toward zero)
    out_q2 = fmt(True, 16, 14)
    pid = ReferencePid(
        make_cfg(output_format=out_q2, output_min=-2.75, output_max=2.75, anti_windup="clamp")
    )
    assert (pid.out_min, pid.out_max) == (-11, 11)
    assert (pid.acc_min, pid.acc_max) == (-2, 2)
    # positive minimum: 0.25 (raw 1) -> ceil(0.25) = 1 (inward, not toward zero)
    pid = ReferencePid(
        make_cfg(output_format=out_q2, output_min=0.25, output_max=2.75, anti_windup="clamp")
    )
    assert (pid.acc_min, pid.acc_max) == (1, 2)
    # integrator finer than output: frac 4, range +-10 -> +-160 exactly
    pid = ReferencePid(
        make_cfg(
            integrator_format=fmt(True, 32, 28),
            output_min=-10.0,
            output_max=10.0,
            anti_windup="clamp",
        )
    )
    assert (pid.acc_min, pid.acc_max) == (-160, 160)
    # integrator narrower than the output range: I8 -> bounds limited to [-128, 127]
    pid = ReferencePid(make_cfg(integrator_format=fmt(True, 8, 8), anti_windup="clamp"))
    assert (pid.acc_min, pid.acc_max) == (-128, 127)


def test_clamp_with_inexact_bound_in_steps():
    # kp = kd = 0, ki = 1, integer integrator, output frac 2 range +-2.75, r = 2, y = 0
    # n0: acc' = 2 <= 2.75 -> 2 (not held); u = 2 -> raw 8 (f2)
    # n1: acc' = 4 > 2.75 -> clamped to 2 (largest integer <= 2.75, held); u = raw 8
    cfg = make_cfg(
        kp=0.0,
        ki=1.0,
        kd=0.0,
        output_format=fmt(True, 16, 14),
        output_min=-2.75,
        output_max=2.75,
        anti_windup="clamp",
    )
    out = run(cfg, [2, 2], [0, 0])
    assert out["i"] == [2, 2]
    assert out["integrator_held"] == [False, True]
    assert out["u"] == [8, 8]
    assert out["u_frac"] == [2, 2]
    assert out["u_saturated"] == [False, False]


# --------------------------------------------------------------------------- API


def test_run_equals_steps_and_reset():
    cfg = _aw_cfg("clamp", kd=3.0)
    r = [5, 9, -4, 0, 12, 12, -20]
    y = [0, 1, 3, -2, 4, 8, 1]
    out = run(cfg, r, y)
    pid = ReferencePid(cfg)
    pid.step(100, 7)  # dirty the state, then reset
    pid.step(-50, 30)
    pid.reset()
    for n, (rn, yn) in enumerate(zip(r, y, strict=True)):
        res = pid.step(rn, yn)
        for key, values in out.items():
            assert res[key] == values[n], (n, key)


def test_config_errors():
    with pytest.raises(ValueError):
        ReferencePid(make_cfg(anti_windup="backcalc"))
    with pytest.raises(ValueError):
        ReferencePid(make_cfg(kp=40000.0))  # outside I16 gains
    with pytest.raises(ValueError):
        ReferencePid(make_cfg(output_min=5.0, output_max=-5.0))
    with pytest.raises(ValueError):
        run(make_cfg(), [0, 1], [0])
