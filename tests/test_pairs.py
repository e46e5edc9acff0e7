"""Point-pair loaders: formats, validation errors naming file/line/field, property-based round trips."""

import json

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from eyetohand import InputError, PointPairs, load_pairs
from eyetohand.core.pairs import load_image_points, pairs_from_records


def write(tmp_path, name, content):
    p = tmp_path / name
    if isinstance(content, bytes):
        p.write_bytes(content)
    else:
        p.write_text(content, encoding="utf-8")
    return p


def test_csv_any_order_extra_columns_and_ids(tmp_path):
    p = write(tmp_path, "p.csv", "note,z,y,x,v,u,id\na,5,2,1,20,10,p1\nb,5,4,3,40,30,p2\n")
    pairs = load_pairs(p)
    assert pairs.ids == ("p1", "p2")
    np.testing.assert_array_equal(pairs.uv_px, [[10, 20], [30, 40]])
    np.testing.assert_array_equal(pairs.xyz_mm, [[1, 2, 5], [3, 4, 5]])
    assert pairs.notes == ()


def test_csv_without_z_is_plane_zero_and_says_so(tmp_path):
    pairs = load_pairs(write(tmp_path, "p.csv", "u,v,x,y\n1,2,3,4\n5,6,7,8\n"))
    assert (pairs.xyz_mm[:, 2] == 0).all()
    assert any("z = 0" in n for n in pairs.notes)
    assert pairs.ids == ("0", "1")


def test_json_pairs(tmp_path):
    doc = {"pairs": [{"u": 1, "v": 2, "x": 3, "y": 4, "z": 5}, {"u": 6, "v": 7, "x": 8, "y": 9, "z": 5}]}
    pairs = load_pairs(write(tmp_path, "p.json", json.dumps(doc)))
    np.testing.assert_array_equal(pairs.xyz_mm[:, 2], [5, 5])


def test_paper_files_load(paper_pairs):
    train, check = paper_pairs
    assert len(train) == 16 and len(check) == 9
    assert np.ptp(train.xyz_mm[:, 2]) == 0


BAD = [
    ("empty.csv", "", r"empty\.csv: empty file"),
    ("hdr.csv", "u,v,x,y,z\n", r"header only"),
    ("miss.csv", "u,v,x\n1,2,3\n", r"line 1: missing column\(s\) y"),
    ("text.csv", "u,v,x,y\n1,2,3,4\n1,abc,3,5\n", r"line 3, field 'v': 'abc' is not a number"),
    ("nan.csv", "u,v,x,y\n1,2,3,4\nnan,2,3,5\n", r"line 3, field 'u': 'nan' is not a finite number"),
    ("inf.csv", "u,v,x,y\n1,2,3,4\n2,2,inf,5\n", r"line 3, field 'x': 'inf' is not a finite number"),
    ("dup.csv", "id,u,v,x,y\na,1,2,3,4\na,5,6,7,8\n", r"line 3, field 'id': duplicate id 'a'"),
    ("rep.csv", "u,v,x,y\n1,2,3,4\n1,2,3,4\n", r"line 3: repeats the \(u, v\) of .*line 2"),
    ("ragged.csv", "u,v,x,y\n1,2,3,4\n5,6,7\n", r"line 3: 3 fields, the header has 4"),
    ("pipe.csv", "u|v|x|y\n1|2|3|4\n", r"line 1: columns separated by '\|', expected ',', ';' or tab"),
    ("mixed.csv", "u;v;x;y\n1,5;2;3;4\n2;3.5;3;5\n", r"line 3, field 'v': '3\.5' has a decimal point"),
    ("trunc.json", '{"pairs": [{"u": 1, "v": 2,', r"trunc\.json line 1: invalid JSON"),
    ("field.json", '{"pairs": [{"u": 1, "v": 2, "x": 3}]}', r"pairs\[0\], field 'y': missing"),
    ("bin.csv", b"\x00\x01\x02\x03u,v", r"binary file"),
    ("latin.csv", "u,v,x,y\n1,2,3,4 \xe9\n".encode("latin-1"), r"line 2: not UTF-8"),
    ("bool.json", '{"pairs": [{"u": true, "v": 2, "x": 3, "y": 4}]}', r"field 'u': True is not a number"),
    (
        "far.csv",
        "u,v,x,y\n1,2,3,4\n2,1e200,3,5\n",
        r"line 3, field 'v': 1e\+200 is more than 1e\+09 px from 0",
    ),
    (
        "farz.csv",
        "u,v,x,y,z\n1,2,3,4,5\n2,3,3,5,-2e9\n",
        r"line 3, field 'z': -2e\+09 is more than 1e\+09 mm from 0",
    ),
]


@pytest.mark.parametrize("name,content,match", BAD, ids=[b[0] for b in BAD])
def test_bad_files_name_file_line_and_field(tmp_path, name, content, match):
    with pytest.raises(InputError, match=match):
        load_pairs(write(tmp_path, name, content))


def test_missing_file(tmp_path):
    with pytest.raises(InputError, match=r"no such file"):
        load_pairs(tmp_path / "nope.csv")


def test_image_points_keep_columns(tmp_path):
    table = load_image_points(write(tmp_path, "in.csv", "name,u,v\na,1,2\nb,3,4\n"))
    out = table.with_columns({"x": np.array([1.5, 2.5]), "y": np.array([0.0, 1.0]), "z": np.zeros(2)})
    assert out.splitlines()[0] == "name,u,v,x,y,z"
    assert out.splitlines()[2].startswith("b,3,4,2.5")


finite = st.floats(min_value=-1e6, max_value=1e6, allow_nan=False, allow_infinity=False)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    st.lists(
        st.tuples(finite, finite, finite, finite, finite),
        min_size=1,
        max_size=20,
        unique_by=(lambda r: (r[0], r[1]), lambda r: (r[2], r[3], r[4])),
    )
)
def test_csv_round_trip_is_exact(tmp_path, rows):
    arr = np.array(rows, float)
    pairs = PointPairs.from_arrays(arr[:, :2], arr[:, 2:])
    p = tmp_path / "rt.csv"
    p.write_text(pairs.to_csv_text())
    back = load_pairs(p)
    np.testing.assert_array_equal(back.uv_px, pairs.uv_px)
    np.testing.assert_array_equal(back.xyz_mm, pairs.xyz_mm)
    assert back.sha256() == pairs.sha256()


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.one_of(st.text(max_size=200), st.binary(max_size=200)))
def test_garbage_raises_only_input_error(tmp_path, content):
    p = tmp_path / "g.csv"
    if isinstance(content, bytes):
        p.write_bytes(content)
    else:
        p.write_text(content, encoding="utf-8")
    try:
        pairs = load_pairs(p)
    except InputError as exc:
        assert "\n" not in str(exc)
    else:  # whatever loads is finite and consistent
        assert np.isfinite(pairs.uv_px).all() and len(pairs.ids) == len(pairs.uv_px)


def test_input_error_carries_its_location_as_attributes(tmp_path):
    """Every interface builds its own form of an error from the same facts, not by parsing text."""
    p = tmp_path / "p.csv"
    p.write_text("u,v,x,y\n1,2,3,4\n5,abc,7,8\n")
    with pytest.raises(InputError) as info:
        load_pairs(p)
    e = info.value
    assert (e.source, e.line, e.field, e.index) == (str(p), 3, "v", None)
    assert e.reason == "'abc' is not a number"
    assert str(e) == f"{p} line 3, field 'v': 'abc' is not a number"
    recs = [{"u": 1, "v": 2, "x": 3, "y": 4}, {"u": True, "v": 2, "x": 3, "y": 5}]
    with pytest.raises(InputError) as info:
        pairs_from_records(recs, source=None, label="check")
    assert info.value.field_path == "check[1].u"
    assert str(info.value) == "check[1], field 'u': True is not a number"


@pytest.mark.parametrize("text", ["6_00", "1_0.5"])
def test_underscore_literals_are_not_numbers(text):
    with pytest.raises(InputError, match="is not a number"):
        pairs_from_records([{"u": text, "v": 2, "x": 3, "y": 4}])


def test_values_too_far_out_for_the_fits_are_refused_by_every_interface(tmp_path, capsys):
    """A pixel or robot coordinate beyond ±1e9 is a typing or unit mistake, and the fits' products
    overflow on it (1e200 gave 'internal error: Singular matrix' on the command line): the pairs are
    refused where they are read, naming the point and field, in the library, the CLI and the API."""
    from fastapi.testclient import TestClient

    from eyetohand.cli import main
    from eyetohand.core.pairs import MAX_ABS_VALUE, PointPairs
    from eyetohand.server.app import create_app

    uv = np.array([[1.0, 2.0], [300.0, 400.0], [500.0, 60.0], [70.0, 800.0]])
    xyz = np.array([[1.0, 2.0, 0.0], [30.0, 40.0, 0.0], [50.0, 6.0, 0.0], [7.0, 80.0, 0.0]])
    PointPairs.from_arrays(uv * (MAX_ABS_VALUE / 800), xyz)  # at the limit: read
    far = xyz.copy()
    far[2, 1] = 1e200
    with pytest.raises(
        InputError, match=r"^<arrays> pairs\[2\], field 'y': 1e\+200 is more than 1e\+09 mm from 0"
    ):
        PointPairs.from_arrays(uv, far)
    path = write(
        tmp_path,
        "far.csv",
        "u,v,x,y\n" + "\n".join(f"{a},{b},{c},{d}" for (a, b), (c, d, _) in zip(uv, far, strict=True)),
    )
    assert main(["calibrate", str(path), "--model", "affine", "-o", str(tmp_path / "c.json")]) == 2
    err = capsys.readouterr().err
    far_words = "1e+200 is more than 1e+09 mm from 0: no robot position is this far out"
    assert err == f"error: {path} line 4, field 'y': {far_words}\n"
    records = [dict(zip("uvxyz", map(float, (*a, *b)), strict=True)) for a, b in zip(uv, far, strict=True)]
    r = TestClient(create_app(tmp_path / "data")).post(
        "/api/calibrations", json={"name": "far", "pairs": records, "model": "affine"}
    )
    assert r.status_code == 422 and r.json()["field"] == "pairs[2].y", r.text
    assert "1e+200 is more than 1e+09 mm from 0" in r.json()["error"]


def test_a_tool_angle_too_far_out_is_refused_where_it_is_read(tmp_path, capsys):
    """The angle column (tool rotations for the tool-centre offset) takes the angle rule of every
    interface: beyond ±1e9 deg a direction is lost to rounding."""
    from eyetohand.cli import main

    path = write(
        tmp_path, "ang.csv", "u,v,x,y,z,angle\n1,2,3,4,5,0\n10,20,30,40,5,1e300\n100,20,30,400,5,0\n"
    )
    assert main(["calibrate", str(path), "-o", str(tmp_path / "c.json")]) == 2
    err = capsys.readouterr().err
    words = "1e+300 deg is more than 1e+09 deg from 0: its direction is lost to rounding"
    assert err == f"error: {path} line 3, field 'angle': {words}\n"


def test_a_singular_system_in_a_fit_is_one_input_error(monkeypatch, paper_pairs):
    """A singular linear system inside a model's estimation that its own checks did not foresee is
    refused as degenerate pairs (one line naming the pairs and the model), not an internal error."""
    from eyetohand.calibration.fit import fit_model
    from eyetohand.core.errors import DegenerateError
    from eyetohand.models import get_model

    def singular(*args, **kwargs):
        raise np.linalg.LinAlgError("Singular matrix")

    monkeypatch.setattr(get_model("homography"), "from_pairs", classmethod(singular))
    with pytest.raises(DegenerateError) as err:
        fit_model(paper_pairs[0], "homography")
    assert str(err.value).endswith("model 'homography' cannot be solved on these pairs (Singular matrix)")
    assert str(err.value).startswith(str(paper_pairs[0].source))
