"""A tampered-file corpus: every JSON path of real calibration files removed, mistyped, reshaped,
perturbed, made NaN / Infinity / huge, the hash changed, the text cut short — and every mutated file is
either refused (one ``error:`` line, exit 2, by every interface that reads calibration files) or, for
the free-text fields that never reach a mapping, loads and maps bit-identically to the original.
No mutated file ever yields a different number or a traceback. A Hypothesis test adds random ones."""

from __future__ import annotations

import copy
import json
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from synth import grid_pairs, make_camera

from eyetohand import Calibration, InputError, calibrate
from eyetohand.cli import main

FREE = ("created_utc", "eyetohand_version", "notes", "warnings", "model.diagnostics")
"""Paths whose mutations may load (they never reach a mapping): the file's free text and the model's
diagnostics. A mutation anywhere else must be refused."""

RECOMPUTED = ("uncertainty.covariance",)
"""Stored copies of what load recomputes from the pairs and uses instead: a change below their
tolerance (1e-6 of sqrt(C_ii C_jj), room for another machine's linear algebra) may load, and
then maps bit-identically because the stored value is never used."""

KEEP_PER_LIST = (0, 1, -1)
"""Entries of long lists that are mutated (the others have the same shape as these)."""


def _make(tmp: Path, name: str) -> Path:
    cam = make_camera(tilt_deg=8, dist=[-0.05, 0, 0, 0, 0])
    heights = (150.0, 210.0) if name == "dlt3d" else (150.0,)
    pairs = grid_pairs(cam, 4, heights=heights, noise_px=0.3, seed=3)
    check = grid_pairs(cam, 3, heights=heights, noise_px=0.3, seed=4, span_mm=100.0)
    cal = calibrate(pairs, name, "lm", check=check, loo=(name == "affine"))
    return cal.save(tmp / f"{name}.json")


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("tamper")
    return {name: _make(tmp, name) for name in ("affine", "homography", "dlt3d")}


def _query(cal: Calibration) -> tuple[np.ndarray, np.ndarray | None]:
    """Pixels over the calibrated region (hull vertices pulled to the centre, and the centre)."""
    hull = cal.region.hull_px
    c = hull.mean(axis=0)
    uv = np.vstack([c, c + 0.8 * (hull - c)])
    z = None if cal.region.z_range_mm is None else np.full(len(uv), float(np.mean(cal.region.z_range_mm)))
    return uv, z


def _fingerprint(cal: Calibration) -> bytes:
    uv, z = _query(cal)
    m = cal.map(uv, z, angle_deg=np.full(len(uv), 30.0))
    return m.xyz_mm.tobytes() + m.rz_deg.tobytes() + m.sigma_mm.tobytes() + m.inside.tobytes()


# ---------------------------------------------------------------- the corpus


def _paths(obj, path=()):
    """Every path into ``obj`` (dict keys and list indices; of long lists only KEEP_PER_LIST)."""
    yield path
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield from _paths(v, (*path, k))
    elif isinstance(obj, list):
        n = len(obj)
        idx = range(n) if n <= len(KEEP_PER_LIST) else sorted({i % n for i in KEEP_PER_LIST})
        for i in idx:
            yield from _paths(obj[i], (*path, i))


def _get(obj, path):
    for k in path:
        obj = obj[k]
    return obj


def _copy_to(doc, path):
    """``doc`` with the containers along ``path[:-1]`` copied (the rest shared, never written), and
    the copy of the last one: the same document a deep copy gives, at a fraction of its cost."""
    out = copy.copy(doc)
    parent = out
    for k in path[:-1]:
        parent[k] = copy.copy(parent[k])
        parent = parent[k]
    return out, parent


def _set(doc, path, value):
    out, parent = _copy_to(doc, path)
    parent[path[-1]] = value
    return out


def _remove(doc, path):
    out, parent = _copy_to(doc, path)
    del parent[path[-1]]
    return out


def _dotted(path) -> str:
    s = ""
    for k in path:
        s += f"[{k}]" if isinstance(k, int) else (f".{k}" if s else str(k))
    return s


def mutations(doc: dict):
    """(label, text) of every mutation of ``doc`` (labels name the path and the kind)."""
    text = json.dumps(doc, indent=2)
    for path in _paths(doc):
        if not path:
            continue
        where = _dotted(path)
        v = _get(doc, path)
        yield f"{where}: removed", json.dumps(_remove(doc, path))
        for bad in ("x", "1.5", True, False, [], {}, None, 0):
            if not (bad == v and isinstance(bad, bool) == isinstance(v, bool)):  # 0 for 0.0 is no change
                yield f"{where}: -> {bad!r}", json.dumps(_set(doc, path, bad))
        if isinstance(v, list):
            if v:
                yield f"{where}: last entry dropped", json.dumps(_set(doc, path, v[:-1]))
                yield f"{where}: last entry repeated", json.dumps(_set(doc, path, [*v, v[-1]]))
            yield f"{where}: wrapped in a list", json.dumps(_set(doc, path, [v]))
        if isinstance(v, (int, float)) and not isinstance(v, bool):
            yield f"{where}: wrapped in a list", json.dumps(_set(doc, path, [v]))
            for rel in (1e-6, 1e-3):
                p = v * (1 + rel) if v != 0 else rel
                if isinstance(v, int):
                    p = v + 1
                yield f"{where}: perturbed {rel:g}", json.dumps(_set(doc, path, p))
            yield f"{where}: huge", json.dumps(_set(doc, path, 1e300))
            yield f"{where}: huge int", json.dumps(_set(doc, path, 10**30))
            for lit in ("NaN", "Infinity", "-Infinity", "1e400"):
                marker = "__LITERAL__"
                yield f"{where}: {lit}", json.dumps(_set(doc, path, marker)).replace(f'"{marker}"', lit)
        if isinstance(v, str) and where != "data_sha256":
            yield f"{where}: changed text", json.dumps(_set(doc, path, v + "x"))
    yield "data_sha256: wrong", json.dumps(_set(doc, ("data_sha256",), "0" * 64))
    for frac in (0.0, 0.1, 0.5, 0.9, 0.999):
        yield f"truncated at {frac:g}", text[: int(len(text) * frac)]
    yield "not JSON", "calibration"
    yield "a JSON list", "[]"


def _is_free(label: str) -> bool:
    where = label.split(":")[0]
    kind = label.split(": ", 1)[-1]
    if (kind.startswith("perturbed") or kind == "-> 0") and any(where.startswith(r) for r in RECOMPUTED):
        return True
    return any(where == f or where.startswith(f + ".") or where.startswith(f + "[") for f in FREE)


def _refused_by_load(path: Path) -> str | None:
    """The one-line refusal, or None when the file loads."""
    try:
        Calibration.load(path)
    except InputError as exc:
        msg = str(exc)
        assert "\n" not in msg and msg, msg
        return msg
    return None


def _cli_refuses(argv, capsys) -> str:
    code = main(argv)
    out, err = capsys.readouterr()
    assert code == 2, (argv, code, out, err)
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    assert "Traceback" not in err and out == "", (out, err)
    return lines[0]


def _interfaces(path: Path, pairs_csv: Path, tmp: Path):
    """argv of every command that reads the calibration file."""
    return [
        ["apply", str(path), "--uv", "1200", "1000", "--json"],
        ["evaluate", str(path), str(pairs_csv)],
        ["report", str(path), "-o", str(tmp / "rep")],
        ["verify", str(path), str(pairs_csv), "--tolerance", "1"],
    ]


@pytest.mark.parametrize("name", ["affine", "homography", "dlt3d"])
@pytest.mark.long
def test_every_mutation_is_refused_or_harmless(files, name, tmp_path, ram_path, capsys):
    orig_path = files[name]
    doc = json.loads(orig_path.read_text())
    original = Calibration.load(orig_path)
    want = _fingerprint(original)
    pairs_csv = tmp_path / "pairs.csv"
    pairs_csv.write_text(original.pairs.to_csv_text())
    loaded, refused, n = [], 0, 0
    f = ram_path / "m.json"  # one file rewritten ~700 times: in memory where the system allows
    for i, (label, text) in enumerate(mutations(doc)):
        n += 1
        f.write_text(text)
        msg = _refused_by_load(f)
        if msg is None:
            assert _is_free(label), f"{label}: loaded, but it is not free text"
            assert _fingerprint(Calibration.load(f)) == want, f"{label}: loaded and maps differently"
            loaded.append(label)
            continue
        refused += 1
        assert str(f) in msg, (label, msg)
        if i % 7 == 0:  # every interface on a seventh of the corpus (they all read through load)
            for argv in _interfaces(f, pairs_csv, tmp_path):
                line = _cli_refuses(argv, capsys)
                assert msg in line, (label, argv, line)
    assert n > 500 and refused > 0.8 * n, (n, refused)
    print(f"{name}: {n} mutations, {refused} refused, {len(loaded)} free-text ones loaded")


# ---------------------------------------------------------------- random mutations


def _leaves(doc):
    return [p for p in _paths(doc) if p]


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_random_mutations(files, data, ram_path):
    name = data.draw(st.sampled_from(sorted(files)))
    doc = json.loads(files[name].read_text())
    want = _fingerprint(Calibration.load(files[name]))
    paths = _leaves(doc)
    m = copy.deepcopy(doc)
    n_edits = data.draw(st.integers(1, 3))
    labels = []
    for _ in range(n_edits):
        path = data.draw(st.sampled_from(paths))
        try:
            _get(m, path)
        except (KeyError, IndexError, TypeError):
            continue
        value = data.draw(
            st.one_of(
                st.none(),
                st.booleans(),
                st.integers(-(10**20), 10**20),
                st.floats(allow_nan=False, allow_infinity=False),
                st.text(max_size=5),
                st.lists(st.floats(-1e3, 1e3), max_size=3),
                st.just("__relative__"),
            )
        )
        old = _get(m, path)
        if value == "__relative__":
            if isinstance(old, bool) or not isinstance(old, (int, float)):
                continue
            value = old * (1 + data.draw(st.floats(1e-9, 1e-2))) if old else 1e-6
        if type(value) is type(old) and value == old and not (isinstance(old, float) and math.isnan(old)):
            continue
        m = _set(m, path, value)
        labels.append(_dotted(path))
    f = ram_path / f"r-{name}.json"
    f.write_text(json.dumps(m))
    msg = _refused_by_load(f)
    if msg is None:
        assert all(_is_free(lbl) for lbl in labels) or m == doc, labels
        assert _fingerprint(Calibration.load(f)) == want, labels


def test_studentized_training_outliers_load(tmp_path):
    """An untampered file whose training outlier flags come from the studentized test (a bumped
    corner pair: flagged only once its leverage is taken into account, or only without it) loads:
    loading re-checks the flags by the rule calibrate used, not by the raw errors."""
    from eyetohand.core.pairs import PointPairs
    from eyetohand.solve.evaluate import stats_from_residuals

    base = grid_pairs(make_camera(tilt_deg=8.0), 5, heights=(10.0,), noise_px=0.2, seed=0)
    for k, bump_mm in ((4, 0.15), (24, 0.3)):
        xyz = base.xyz_mm.copy()
        xyz[k, 0] += bump_mm
        pairs = PointPairs.from_arrays(base.uv_px, xyz)
        cal = calibrate(pairs, model="homography", loo=False)
        raw = stats_from_residuals(cal.model.residuals(pairs.uv_px, pairs.xyz_mm), pairs.ids)
        assert raw.outliers != cal.train.outliers  # the case this test is about
        path = cal.save(tmp_path / f"bumped-{k}.json")
        assert Calibration.load(path).train.outliers == cal.train.outliers


@pytest.mark.parametrize("where", [("uncertainty", "noise_mm"), ("train", "rms_mm"), ("region", "margin_px")])
def test_an_intact_file_this_version_does_not_reproduce_is_not_called_changed(files, where, tmp_path, capsys):
    """A file whose content still matches its content_sha256 is as it was written. If this eyetohand
    then does not reproduce what it records (an older one computed it otherwise), the refusal says so
    — with the version that wrote it — instead of "changed after it was written"; an edit that leaves
    the hash stale is still called a change. The command line says the same words."""
    from eyetohand.calibration.file import content_sha256

    doc = json.loads(files["homography"].read_text())
    assert isinstance(doc[where[0]][where[1]], float), where
    doc[where[0]][where[1]] *= 1.001
    stale = tmp_path / "edited.json"
    stale.write_text(json.dumps(doc))
    doc["content_sha256"] = content_sha256(doc)
    doc["eyetohand_version"] = "0.0.9"
    sealed = tmp_path / "older.json"
    sealed.write_text(json.dumps(doc))
    with pytest.raises(InputError) as edited:
        Calibration.load(stale)
    assert str(edited.value).endswith(
        ("the file was changed after it was written", "changed or damaged after it was written")
    ), edited.value
    with pytest.raises(InputError) as older:
        Calibration.load(sealed)
    words = str(older.value)
    assert f"'{where[0]}.{where[1]}'" in words or where[0] == "train", words
    assert "the file is as written (its content_sha256 checks)" in words
    assert "the eyetohand that wrote it (0.0.9) computed this differently" in words
    assert "changed after it was written" not in words and "\n" not in words
    assert main(["apply", str(sealed), "--uv", "1", "2"]) == 2
    assert capsys.readouterr().err.strip() == f"error: {words}"


@pytest.mark.parametrize(
    ("text", "words"),
    [
        ('"fit": {"x": [1.0, 1e400]}', "field 'fit.x[1]': inf is not a finite number"),
        ('"a": [{"b": -1e999}]', "field 'a[0].b': -inf is not a finite number"),
        ('"n": 100000000000000000000', "field 'n': 100000000000000000000 is too large a number"),
    ],
)
def test_a_number_json_allows_but_a_float_cannot_hold_is_named(tmp_path, text, words):
    """The file's numbers are checked in one pass without field names; the one that fails is then
    named by its path (each of these fails on that check, before anything else is read)."""
    f = tmp_path / "n.json"
    f.write_text('{"schema": "eyetohand.calibration", "schema_version": 2, ' + text + "}")
    with pytest.raises(InputError) as err:
        Calibration.load(f)
    assert str(err.value) == f"{f}: {words}", err.value


def test_numbers_of_other_types_are_checked_with_their_names():
    """Values that are not what ``json.loads`` gives (a dict built in code with NumPy numbers) take
    the walk with names, so a NumPy infinity is refused like a parsed one."""
    from eyetohand.calibration.fields import check_numbers as _check_numbers

    _check_numbers({"a": [np.float64(1.5), 2, "x", None, True]}, "")
    with pytest.raises(InputError, match=r"^field 'a\[1\]': inf is not a finite number$"):
        _check_numbers({"a": [np.float64(1.5), np.float64("inf")]}, "")
