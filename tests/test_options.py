"""Solver options: every field range-checked where it is made, config files and ``--set`` parsed
to a valid ``Options`` or one clean InputError, options larger than the data clamped."""

import json
import math
import os
from dataclasses import fields
from enum import Enum

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dloe_sfm.config import MAX_CONFIG_BYTES, load_options
from dloe_sfm.core.capture import Capture, project
from dloe_sfm.core.options import RULES, Clocks, Distance, Embedding, Options, RobustLoss
from dloe_sfm.core.solver import reconstruct
from dloe_sfm.errors import InputError
from dloe_sfm.synth import ring_cameras

NAMES = [f.name for f in fields(Options)]
INF, NAN = math.inf, math.nan


def _real(lo, hi=INF, *, lo_open=False, hi_open=True):
    def ok(v):
        above = v > lo if lo_open else v >= lo
        below = v < hi if hi_open else v <= hi
        return type(v) is float and above and below

    return ok


def _int(lo, hi):
    return lambda v: type(v) is int and lo <= v <= hi


def _flag(v):
    return type(v) is bool


# what every field may hold once set, written out independently of options.RULES
VALID = {
    "lambda1": _real(0.0),
    "lambda2": lambda v: v is None or _real(0.0, lo_open=True, hi_open=False)(v),
    "noise_px": lambda v: v == "auto" or _real(0.0)(v),
    "lambda3": _real(0.0),
    "ridge": _real(0.0),
    "prior_weight": _real(0.0, 1.0, hi_open=False),
    "degree_floor": _real(0.0, 1.0, hi_open=False),
    "fixed_degree": _flag,
    "end_degree": _real(0.0, 1.0, hi_open=False),
    "num_candidates": _int(2, 10_000),
    "min_ray_angle": _real(0.0, 90.0),
    "spectral_prior": _flag,
    "omega": _real(0.0, 2.0, lo_open=True),
    "resequence_every": _int(1, 10**6),
    "distance": lambda v: type(v) is Distance,
    "embedding": lambda v: type(v) is Embedding,
    "max_iterations": _int(1, 10**6),
    "soft_iterations": _int(0, 10**6),
    "tolerance": _real(0.0),
    "cost_tolerance": _real(0.0),
    "stream_clocks": lambda v: type(v) is Clocks,
    "shared_rate": _flag,
    "stream_offsets": _flag,
    "robust_loss": lambda v: type(v) is RobustLoss,
    "robust_scale_px": lambda v: v is None or _real(0.0, lo_open=True)(v),
    "robust_iterations": _int(0, 10**6),
    "fix_swaps": _flag,
    "segment_events": _flag,
    "workers": lambda v: v == "auto" or _int(1, 10**6)(v),
    "window_images": lambda v: v == "auto" or _int(0, 10**6)(v),
}


def assert_valid(opts):
    assert isinstance(opts, Options)
    bad = {n: getattr(opts, n) for n in NAMES if not VALID[n](getattr(opts, n))}
    assert not bad, bad


def assert_one_line(err: InputError):
    text = str(err)
    assert text and len(text.splitlines()) == 1 and len(text) < 2000, text


def test_every_field_has_a_rule_and_a_documented_range():
    assert list(RULES) == NAMES == list(VALID)
    assert_valid(Options())
    # the defaults are the documented ones (a rule must not normalise them away)
    assert Options().to_dict()["num_candidates"] == 8 and Options().omega == 1.9


# (field, bad value, the allowed range the message must give); every field at least once
BAD = [
    ("lambda1", -1, "a finite number >= 0"),
    ("lambda1", INF, "a finite number >= 0"),
    ("lambda1", "1e-5", "a finite number >= 0"),
    ("lambda2", 0, "None or a number > 0 (inf allowed)"),
    ("lambda2", NAN, "None or a number > 0 (inf allowed)"),
    ("lambda2", -INF, "None or a number > 0 (inf allowed)"),
    ("noise_px", -5, "auto or a finite number >= 0"),
    ("noise_px", INF, "auto or a finite number >= 0"),
    ("workers", 0, "auto or an integer in [1, 1000000]"),
    ("workers", 2.5, "auto or an integer in [1, 1000000]"),
    ("window_images", -1, "auto or an integer in [0, 1000000]"),
    ("lambda3", NAN, "a finite number >= 0"),
    ("ridge", -1e-9, "a finite number >= 0"),
    ("prior_weight", 5, "a number in [0, 1]"),
    ("prior_weight", None, "a number in [0, 1]"),
    ("degree_floor", 5, "a number in [0, 1]"),
    ("degree_floor", -0.1, "a number in [0, 1]"),
    ("fixed_degree", 0.5, "true or false"),
    ("fixed_degree", 1, "true or false"),
    ("fixed_degree", "yes", "true or false"),
    ("end_degree", -1, "a number in [0, 1]"),
    ("num_candidates", 0, "an integer in [2, 10000]"),
    ("num_candidates", -3, "an integer in [2, 10000]"),
    ("num_candidates", 1, "an integer in [2, 10000]"),
    ("num_candidates", 1_000_000_000, "an integer in [2, 10000]"),
    ("num_candidates", 2.5, "an integer in [2, 10000]"),
    ("num_candidates", 8.0, "an integer in [2, 10000]"),
    ("num_candidates", True, "an integer in [2, 10000]"),
    ("num_candidates", 10**5000, "an integer in [2, 10000]"),
    ("min_ray_angle", 90, "a number in [0, 90)"),
    ("min_ray_angle", -1, "a number in [0, 90)"),
    ("spectral_prior", None, "true or false"),
    ("omega", NAN, "a number in (0, 2)"),
    ("omega", 0, "a number in (0, 2)"),
    ("omega", 2, "a number in (0, 2)"),
    ("resequence_every", 0, "an integer in [1, 1000000]"),
    ("distance", "manhattan", "one of arc, euclidean"),
    ("distance", 1, "one of arc, euclidean"),
    ("embedding", "x", "one of spectral, mds, shp, affine"),
    ("embedding", Distance.ARC, "one of spectral, mds, shp, affine"),
    ("max_iterations", 0, "an integer in [1, 1000000]"),
    ("max_iterations", -1, "an integer in [1, 1000000]"),
    ("max_iterations", 10**7, "an integer in [1, 1000000]"),
    ("soft_iterations", -5, "an integer in [0, 1000000]"),
    ("tolerance", NAN, "a finite number >= 0"),
    ("cost_tolerance", -1e-5, "a finite number >= 0"),
    ("stream_clocks", "maybe", "one of auto, on, off (or true / false)"),
    ("stream_clocks", 2, "one of auto, on, off (or true / false)"),
    ("shared_rate", np.float64(1.0), "true or false"),
    ("stream_offsets", "yes", "true or false"),
    ("robust_loss", "l1", "one of cauchy, huber, none"),
    ("robust_scale_px", 0, "None or a finite number > 0"),
    ("robust_scale_px", INF, "None or a finite number > 0"),
    ("robust_iterations", -1, "an integer in [0, 1000000]"),
    ("fix_swaps", [True], "true or false"),
    ("segment_events", {"a": 1}, "true or false"),
]


def test_the_bad_table_covers_every_field():
    assert {name for name, _, _ in BAD} == set(NAMES)


@pytest.mark.parametrize(("name", "value", "allowed"), BAD,
                         ids=[f"{name}-{i}" for i, (name, _, _) in enumerate(BAD)])
def test_a_bad_value_is_an_input_error_naming_the_field_and_its_range(name, value, allowed):
    with pytest.raises(InputError) as e:
        Options(**{name: value})
    assert str(e.value).startswith(f"option '{name}' must be {allowed}, got "), str(e.value)
    assert_one_line(e.value)
    assert isinstance(e.value, ValueError)  # what a Python API user catches
    opts = Options()
    with pytest.raises(InputError, match=f"option '{name}' must be"):
        opts.replace(**{name: value})
    with pytest.raises(InputError, match=f"option '{name}' must be"):
        setattr(opts, name, value)  # a later assignment is checked too, and changes nothing
    assert opts == Options()


# the reproductions of issue 12, as typed on the command line
BAD_SETS = [
    ("num_candidates=0", "an integer in [2, 10000], got 0"),
    ("num_candidates=-3", "an integer in [2, 10000], got -3"),
    ("num_candidates=1000000000", "an integer in [2, 10000], got 1000000000"),
    ("max_iterations=0", "an integer in [1, 1000000], got 0"),
    ("max_iterations=-1", "an integer in [1, 1000000], got -1"),
    ("min_ray_angle=90", "a number in [0, 90), got 90.0"),
    ("noise_px=-5", "auto or a finite number >= 0, got -5.0"),
    ("omega=nan", "a number in (0, 2), got nan"),
    ("tolerance=nan", "a finite number >= 0, got nan"),
    ("lambda1=-1", "a finite number >= 0, got -1.0"),
    ("prior_weight=5", "a number in [0, 1], got 5.0"),
    ("end_degree=-1", "a number in [0, 1], got -1.0"),
    ("soft_iterations=-5", "an integer in [0, 1000000], got -5"),
    ("robust_iterations=-1", "an integer in [0, 1000000], got -1"),
    ("degree_floor=5", "a number in [0, 1], got 5.0"),
    ("resequence_every=0", "an integer in [1, 1000000], got 0"),
    ("num_candidates=2.5", "an integer in [2, 10000], got '2.5'"),
    ("noise_px=inf", "auto or a finite number >= 0, got inf"),
    ("noise_px=none", "auto or a finite number >= 0, got 'none'"),
    ("lambda2=-inf", "None or a number > 0 (inf allowed), got -inf"),
    ("segment_events=maybe", "true or false, got 'maybe'"),
    ("embedding=x", "one of spectral, mds, shp, affine, got 'x'"),
]


@pytest.mark.parametrize(("item", "message"), BAD_SETS)
def test_a_bad_set_names_the_argument_the_option_and_its_range(item, message):
    with pytest.raises(InputError) as e:
        load_options(None, [item])
    key = item.split("=")[0]
    assert str(e.value) == f"--set {item}: option '{key}' must be {message}"


@pytest.mark.parametrize(("item", "meant"), [
    ("noise_pix=2", "noise_px"), ("lamda1=3", "lambda1"), ("max_iteration=5", "max_iterations"),
])
def test_a_misspelt_option_is_answered_with_the_one_meant(tmp_path, item, meant):
    key = item.split("=")[0]
    with pytest.raises(InputError) as e:
        load_options(None, [item])
    assert str(e.value) == f"--set {item}: unknown option '{key}': did you mean '{meant}'?"
    cfg = tmp_path / "solver.toml"
    cfg.write_text(f"[solver]\n{key} = {item.split('=')[1]}\n")
    with pytest.raises(InputError) as e:
        load_options(cfg)
    assert str(e.value) == f"{cfg} [solver]: unknown option '{key}': did you mean '{meant}'?"


def test_set_syntax_and_unknown_keys():
    with pytest.raises(InputError, match=r"^--set omega: expected key=value$"):
        load_options(None, ["omega"])
    with pytest.raises(InputError, match=r"^--set zebra=3: unknown option 'zebra' \(known: "):
        load_options(None, ["zebra=3"])
    with pytest.raises(InputError) as e:  # an echoed newline stays escaped: one line
        load_options(None, ["omega=1\nall good"])
    assert_one_line(e.value)
    with pytest.raises(InputError, match="unknown option"):
        Options().replace(omegaa=1.0)


VALID_EDGES = [
    ("lambda1", 0, 0.0),
    ("lambda2", INF, INF),
    ("lambda2", 1e-300, 1e-300),
    ("lambda2", None, None),
    ("noise_px", np.float32(2.0), 2.0),
    ("noise_px", "Auto", "auto"),
    ("prior_weight", 1, 1.0),
    ("degree_floor", 0.0, 0.0),
    ("end_degree", 1.0, 1.0),
    ("num_candidates", np.int64(10_000), 10_000),
    ("num_candidates", 2, 2),
    ("min_ray_angle", 89.99, 89.99),
    ("omega", 1.999, 1.999),
    ("omega", 1e-3, 1e-3),
    ("resequence_every", 1, 1),
    ("max_iterations", 10**6, 10**6),
    ("soft_iterations", 0, 0),
    ("robust_iterations", 0, 0),
    ("tolerance", 0, 0.0),
    ("robust_scale_px", 0.5, 0.5),
    ("embedding", "MDS", Embedding.MDS),
    ("distance", Distance.EUCLIDEAN, Distance.EUCLIDEAN),
    ("stream_clocks", True, Clocks.ON),
    ("stream_clocks", "false", Clocks.OFF),
    ("robust_loss", "none", RobustLoss.NONE),
    ("fix_swaps", np.bool_(False), False),
]


@pytest.mark.parametrize(("name", "value", "stored"), VALID_EDGES)
def test_valid_edge_values_are_accepted_and_stored_normalised(name, value, stored):
    opts = Options(**{name: value})
    assert_valid(opts)
    got = getattr(opts, name)
    assert got == stored and type(got) is type(stored)
    assert Options().replace(**{name: value}) == opts


def _some_options() -> list[Options]:
    return [
        Options(),
        Options(lambda2=INF, robust_scale_px=2.5, embedding="spectral", stream_clocks="on",
                num_candidates=12, omega=1.0, fixed_degree=False, tolerance=0.0),
        Options(noise_px=2.0, lambda1=1.0 / 3.0, distance="euclidean", robust_loss="huber",
                shared_rate=True, segment_events=False, max_iterations=7, soft_iterations=0),
    ]


@pytest.mark.parametrize("opts", _some_options())
def test_replace_and_to_dict_round_trip(opts):
    assert opts.replace() == opts and opts.replace() is not opts
    assert Options(**opts.to_dict()) == opts
    sets = [f"{k}={v}" for k, v in opts.to_dict().items()]
    assert load_options(None, sets) == opts
    assert load_options(None, sets, base=Options(omega=0.5, num_candidates=3)) == opts


# config files: (bytes, the message's end); the message always starts with the file's name
BAD_CONFIGS = [
    (b"solver = 5\n", "'solver' must be a table ([solver]), got 5"),
    (b"solver = [1, 2]\n", "'solver' must be a table ([solver]), got [1, 2]"),
    (b"omega = [1, 2]\n", "option 'omega' must be a number in (0, 2), got [1, 2]"),
    (b"omega = {a = 1}\n", "option 'omega' must be a number in (0, 2), got {'a': 1}"),
    (b"omega = '1.5'\n", "option 'omega' must be a number in (0, 2), got '1.5'"),
    (b"omega = nan\n", "option 'omega' must be a number in (0, 2), got nan"),
    (b"[solver]\nmax_iterations = true\n",
     "[solver]: option 'max_iterations' must be an integer in [1, 1000000], got True"),
    (b"num_candidates = 3.0\n",
     "option 'num_candidates' must be an integer in [2, 10000], got 3.0"),
    (b"fixed_degree = 1\n", "option 'fixed_degree' must be true or false, got 1"),
    (b"fixed_degree = 'true'\n", "option 'fixed_degree' must be true or false, got 'true'"),
    (b"when = 1979-05-27\n", "unknown option 'when'"),
    (b"noise_px = 1979-05-27\n", "option 'noise_px' must be auto or a finite number >= 0, got "),
    (b"[solver]\nomega = 1\n[other]\nx = 1\n", "unknown key 'other' beside the [solver] table"),
    (b"omega = \n", "invalid TOML (Invalid value (at line 1, column 9))"),
    (b"omega = 1.5\n\xff\xfe\n", "not UTF-8 text (bad byte at offset 12)"),
    (b"a = " + b"[" * 100_000 + b"]" * 100_000, "invalid TOML (nested too deeply)"),
    (b"#" * (MAX_CONFIG_BYTES + 1), f"larger than {MAX_CONFIG_BYTES} bytes, not a solver config"),
]


@pytest.mark.parametrize(("content", "message"), BAD_CONFIGS,
                         ids=[f"config-{i}" for i in range(len(BAD_CONFIGS))])
def test_a_bad_config_file_is_one_line_naming_the_file_and_key(tmp_path, content, message):
    cfg = tmp_path / "solver.toml"
    cfg.write_bytes(content)
    with pytest.raises(InputError) as e:
        load_options(cfg)
    assert str(e.value).startswith(f"{cfg}") and message in str(e.value), str(e.value)
    assert_one_line(e.value)


def test_a_config_that_is_not_a_file(tmp_path):
    with pytest.raises(InputError, match="is a directory, not a config file"):
        load_options(tmp_path)
    with pytest.raises(InputError, match="no such config file"):
        load_options(tmp_path / "missing.toml")
    fifo = tmp_path / "fifo.toml"
    os.mkfifo(fifo)  # reading it would block for ever
    with pytest.raises(InputError, match="not a regular file"):
        load_options(fifo)
    with pytest.raises(InputError) as e:
        load_options(tmp_path / "new\nline.toml")
    assert_one_line(e.value)


def test_valid_odd_config_files(tmp_path):
    cfg = tmp_path / "solver.toml"
    cfg.write_bytes(b"\xef\xbb\xbf[solver]\r\nlambda1 = 1\r\nstream_clocks = false\r\n"
                    b"lambda2 = 'None'\r\nrobust_scale_px = inf\r\n")
    with pytest.raises(InputError, match="'robust_scale_px' must be None or a finite number > 0"):
        load_options(cfg)
    cfg.write_bytes(cfg.read_bytes().replace(b"inf", b"2"))
    opts = load_options(cfg, ["lambda2=none"], base=Options(lambda2=5.0, robust_scale_px=1.0))
    assert opts == Options(lambda1=1.0, stream_clocks="off", robust_scale_px=2.0)
    assert type(opts.lambda1) is float  # a TOML integer for a number option is fine


# --- hypothesis: any --set / config file gives a valid Options or one clean InputError ---

KEYS = st.one_of(st.sampled_from([*NAMES, "solver"]), st.text(max_size=12))
WORDS = st.sampled_from(["none", "None", "nan", "inf", "-inf", "-5", "0", "1", "2", "1e9",
                         "true", "False", "on", "off", "yes", "MDS", "affine", "huber", "auto",
                         "2.5", "0.5", "89.9", "1_000", " 3 ", ""])
SET_VALUES = st.one_of(WORDS, st.text(max_size=12), st.integers().map(str),
                       st.floats().map(repr))


def _good(name: str):
    """Values inside option ``name``'s range, so that whole inputs are often valid too."""
    default = getattr(Options(), name)
    if isinstance(default, bool):
        return st.booleans()
    if isinstance(default, Enum):
        return st.sampled_from([m.value for m in type(default)])
    if isinstance(default, int):
        return st.integers(2, 50)
    return st.floats(0.01, 1.0)  # inside every number option's range


GOOD = st.sampled_from(NAMES).flatmap(lambda n: st.tuples(st.just(n), _good(n)))


def _outcome(call):
    """The Options ``call`` returns (checked valid), or None after a one-line InputError."""
    try:
        opts = call()
    except InputError as e:
        assert_one_line(e)
        return None
    assert_valid(opts)
    return opts


@settings(max_examples=100, deadline=None)
@given(st.lists(st.one_of(GOOD.map(lambda kv: f"{kv[0]}={kv[1]}"),
                          st.tuples(KEYS, SET_VALUES).map("=".join), st.text(max_size=20)),
                max_size=4))
def test_any_set_gives_valid_options_or_a_clean_error(items):
    _outcome(lambda: load_options(None, items))


TOML_SCALARS = st.one_of(
    st.integers(-(2**63), 2**63 - 1), st.floats(), st.booleans(), st.text(max_size=8),
    st.sampled_from(["none", "mds", "on", "cauchy", "euclidean"]),
    st.floats(0, 3), st.integers(-2, 12),
)
TOML_VALUES = st.recursive(
    TOML_SCALARS,
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=4), inner,
                                                                 max_size=3),
    max_leaves=6,
)


SCOPED = HealthCheck.function_scoped_fixture  # tmp_path: each example rewrites its one file


def _toml(value) -> str:
    """``value`` as a TOML inline value (strings and keys as JSON-escaped basic strings)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return "nan" if math.isnan(value) else repr(value)
    if isinstance(value, int):
        return str(value)
    if isinstance(value, str):
        return json.dumps(value, ensure_ascii=False)
    if isinstance(value, list):
        return "[" + ", ".join(_toml(v) for v in value) + "]"
    return "{" + ", ".join(f"{_toml(k)} = {_toml(v)}" for k, v in value.items()) + "}"


@settings(max_examples=100, deadline=None, suppress_health_check=[SCOPED])
@given(table=st.lists(st.one_of(GOOD, GOOD, st.tuples(KEYS, TOML_VALUES)), max_size=5).map(dict),
       solver=st.booleans(),
       tail=st.binary(max_size=12), garbled=st.booleans())
def test_any_config_file_gives_valid_options_or_a_clean_error(tmp_path, table, solver, tail,
                                                              garbled):
    lines = [f"{_toml(k)} = {_toml(v)}" for k, v in table.items()]
    text = ("[solver]\n" if solver else "") + "\n".join(lines) + "\n"
    cfg = tmp_path / "fuzz.toml"
    cfg.write_bytes(text.encode() + (tail if garbled else b""))
    _outcome(lambda: load_options(cfg, ["omega=1.5"]))


@settings(max_examples=60, deadline=None, suppress_health_check=[SCOPED])
@given(raw=st.binary(max_size=300))
def test_any_bytes_as_config_give_valid_options_or_a_clean_error(tmp_path, raw):
    cfg = tmp_path / "bytes.toml"
    cfg.write_bytes(raw)
    _outcome(lambda: load_options(cfg))


# --- options against the data: clamped, or an error naming the option ---


def tiny_capture(n_per_stream=5, streams=3, p=5):
    """Points moving linearly, seen by a ring of cameras at interleaved instants (15 images)."""
    rng = np.random.default_rng(0)
    K, R, C = ring_cameras(np.zeros(3), num=streams, radius=3.0)
    stream = np.repeat(np.arange(streams), n_per_stream)
    frame = np.tile(np.arange(n_per_stream), streams)
    t = frame + stream / streams
    X = rng.standard_normal((p, 3))[None] * 0.3 + t[:, None, None] * 0.02
    x = project(X, K[stream], R[stream], C[stream])
    return Capture(x=x, K=K[stream], R=R[stream], C=C[stream], stream=stream,
                   frame=frame).validate()


FAST = Options(max_iterations=6, robust_iterations=1)


def test_more_candidates_than_images_are_clamped():
    cap = tiny_capture()
    n = cap.num_images
    huge = reconstruct(cap, FAST.replace(num_candidates=10_000))
    clamped = reconstruct(cap, FAST.replace(num_candidates=n - 1))
    assert np.array_equal(huge.X, clamped.X) and np.array_equal(huge.order, clamped.order)
    assert (huge.W != clamped.W).nnz == 0
    assert np.array_equal(huge.cost_history, clamped.cost_history)


def test_a_ray_angle_no_pair_reaches_is_an_error_naming_the_option():
    cap = tiny_capture()  # three cameras 120 degrees apart: 60 degrees from antiparallel
    with pytest.raises(InputError, match=r"at least 75 degrees .*\(option 'min_ray_angle'\)"):
        reconstruct(cap, FAST.replace(min_ray_angle=75.0))
    assert np.isfinite(reconstruct(cap, FAST.replace(min_ray_angle=55.0)).X).all()


@pytest.mark.parametrize("changes", [
    {"lambda2": 1e300},  # a soft ray weight beyond precision: hard rays
    {"noise_px": 1e-300},  # its ray weight overflows to inf: hard rays
    {"robust_scale_px": 1e-300, "noise_px": 1.0},  # would drop every observation: not run
])
def test_extreme_valid_values_solve(changes):
    cap = tiny_capture()
    result = reconstruct(cap, FAST.replace(**changes))
    assert np.isfinite(result.X).all() and result.outliers.size == 0
