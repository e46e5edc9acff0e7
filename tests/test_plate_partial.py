"""A ChArUco board seen in part (issue 37): covered by a blank rectangle over a third of it, or partly
out of the image — its corners seen keep their ids, the touches snap to them, the calibration checks
within its sigma against check points, the file keeps the ids seen and refuses them edited; too few
corners are refused in words that give the count, the minimum and why."""

from __future__ import annotations

import json

import numpy as np
import pytest

from eyetohand.calibration import Calibration, calibrate_plate
from eyetohand.calibration.plate import touches_again
from eyetohand.calibration.plate_record import PlateImage
from eyetohand.calibration.touches import touches_from_text
from eyetohand.core import InputError, pairs_from_text
from eyetohand.sim import simulate_plate
from eyetohand.vision import MIN_SEEN, PlateNotFound, PlateSpec, annotate_plate, detect_plate

SPEC = "charuco:9x6:15"


@pytest.fixture(scope="module")
def board_px():
    """The whole board's corners in the image (the truth, no image rendered): where to cover it."""
    uv = simulate_plate(spec=SPEC, seed=3, render=False).true_uv_px
    return uv.min(axis=0), uv.max(axis=0)


def _middle_third(board_px) -> tuple[float, float, float, float]:
    (u0, _), (u1, _) = board_px
    return (u0 + (u1 - u0) / 3, 0.0, u0 + 2 * (u1 - u0) / 3, 2047.0)


@pytest.fixture(scope="module", params=["covered", "out of view"])
def partial(request, board_px):
    if request.param == "covered":  # a blank rectangle over the middle third of the board
        sim = simulate_plate(spec=SPEC, seed=3, touch_noise_mm=0.05, cover_px=_middle_third(board_px))
    else:  # the board's right ~third beyond the image's edge (the board is ~10 px/mm, 1350 px wide)
        sim = simulate_plate(spec=SPEC, seed=3, touch_noise_mm=0.05, shift_mm=(100.0, 0.0))
        assert (sim.true_uv_px[:, 0] > sim.camera.image_size[0]).sum() >= 12  # really out of the image
    return request.param, sim, detect_plate(sim.image, SPEC, "plate.png")


def test_partial_board_corners_keep_their_ids(partial):
    how, sim, det = partial
    seen = det.seen
    assert MIN_SEEN <= seen.sum() < 0.8 * det.spec.n_points, seen.sum()
    err = np.linalg.norm(det.uv_px[seen] - sim.true_uv_px[seen], axis=1)  # by id: the truth's numbering
    assert np.sqrt(np.mean(err**2)) < 0.05 and err.max() < 0.15, (how, err)
    assert np.isnan(det.uv_px[~seen]).all()
    if how == "covered":  # nothing seen under the cover
        (u0, _), (u1, _) = sim.true_uv_px.min(axis=0), sim.true_uv_px.max(axis=0)
        mid = (sim.true_uv_px[:, 0] > u0 + 0.4 * (u1 - u0)) & (sim.true_uv_px[:, 0] < u0 + 0.6 * (u1 - u0))
        assert mid.any() and not (seen & mid).any()
    else:
        assert not seen[sim.true_uv_px[:, 0] > sim.camera.image_size[0]].any()


def test_labels_are_the_extreme_corners_seen():
    s = PlateSpec.parse(SPEC)
    assert s.corner_labels() == {"A": 0, "B": 8, "C": 53, "D": 45}
    assert s.corner_labels(np.ones(54, bool)) == s.corner_labels()
    seen = np.zeros(54, bool)
    r, c = np.divmod(np.arange(54), 9)
    seen[(c <= 5) & (r >= 1)] = True  # rows 1-5, columns 0-5
    seen[s.index_of("r1c0")] = False
    assert {k: s.ids()[i] for k, i in s.corner_labels(seen).items()} == {
        "A": "r1c1",  # least row + col: r1c1 (r2c0 ties; the first numbered wins)
        "B": "r1c5",
        "C": "r5c5",
        "D": "r5c0",
    }
    with pytest.raises(
        InputError, match=r"'r6c0' is not a point of plate charuco:9x6:15:11.25 \(r0c0 .. r5c8\)"
    ):
        s.index_of("r6c0")


def test_partial_board_calibrates_within_its_sigma(partial, tmp_path):
    how, sim, det = partial
    touches = touches_from_text(sim.touches_csv, "touches.csv", ["plate.png"])
    check = pairs_from_text(sim.check_csv, "check.csv")
    assert len(check) >= 10
    cal = calibrate_plate([sim.image], SPEC, touches, check=check, names=["plate.png"])
    assert cal.plate is not None and len(cal.pairs) == det.seen.sum()
    ids = np.array(det.spec.ids())
    assert cal.pairs.ids == tuple(ids[det.seen])  # the pairs are named by the corners' ids
    assert any(f"{det.seen.sum()} of its 54 corners seen" in n for n in cal.notes)
    # the touches (the simulation's extreme corners in view) snapped to corners seen; the labels too
    labels = det.spec.corner_labels(det.seen)
    assert det.seen[list(cal.plate.placements[0].corners)].all() and det.seen[list(labels.values())].all()
    m = cal.map(check.uv_px)
    err = np.linalg.norm((m.xyz_mm - check.xyz_mm)[:, :2], axis=1)
    # the touches' error is shared by all points: the check error is one draw of it, within ~3 sigma
    assert (err < 3 * m.sigma_mm).all(), (how, err, m.sigma_mm)
    assert np.sqrt(np.mean(err**2)) < 0.1
    # the annotated image: the labels on the corners seen
    out = annotate_plate(sim.image, det.spec, det.uv_px)
    assert out.shape == (*sim.image.shape, 3)
    u, v = det.uv_px[labels["A"]]
    patch = out[round(v) - 12 : round(v) + 12, round(u) - 12 : round(u) + 12].astype(int)
    assert (patch[..., 0] != patch[..., 1]).any()  # coloured (the label's yellow ring) on the grey image

    # the file: the ids seen are stored, round-trip bit-identically, and an edited id list is refused
    path = tmp_path / "cal.json"
    cal.save(path)
    again = Calibration.load(path)
    assert np.array_equal(again.map(check.uv_px).xyz_mm, m.xyz_mm)
    assert np.array_equal(again.map(check.uv_px).sigma_mm, m.sigma_mm)
    d = json.loads(path.read_text())
    img = d["plate"]["images"][0]
    assert img["ids"] == list(ids[det.seen]) and len(img["uv_px"]) == det.seen.sum()
    again.save(tmp_path / "again.json")
    assert (tmp_path / "again.json").read_bytes() == path.read_bytes()
    from eyetohand.calibration.file import content_sha256

    def shifted(p):  # every id one column on: the points named differently
        p["images"][0]["ids"] = [f"r{i[1]}c{int(i.split('c')[1]) + 1}" for i in p["images"][0]["ids"]]

    swapped_first = ids[det.seen][1]
    for edit, words in (
        (
            lambda p: p["images"][0]["ids"].__setitem__(0, swapped_first),
            "distinct points in the plate's order",
        ),
        (lambda p: p["images"][0]["ids"].__setitem__(0, "r9c0"), "'r9c0' is not a point of plate"),
        (lambda p: p["images"][0]["ids"].pop(), r"uv_px' must be \d+ points \(u, v\), one per id"),
        (lambda p: p["images"][0]["ids"].__setitem__(0, "zz"), "'zz' is not a point of plate"),
        (lambda p: p["images"][0].pop("ids"), r"uv_px' must be 54 points"),
        (shifted, "field 'plate"),
    ):
        bad = json.loads(path.read_text())
        try:
            edit(bad["plate"])
        except (ValueError, IndexError):  # the shift ran off the board: that edit is covered by r9c0
            continue
        bad["content_sha256"] = content_sha256(bad)  # edited and resealed
        with pytest.raises(InputError, match=words):
            Calibration.from_dict(bad, "cal.json")


def test_too_few_corners_are_refused_with_the_minimum_and_why(board_px):
    (u0, v0), (u1, v1) = board_px
    # everything but the board's top-left corner region covered: a handful of corners at most
    sim = simulate_plate(
        spec=SPEC, seed=3, cover_px=(u0 + 0.25 * (u1 - u0), 0.0, 2447.0, 2047.0), n_touches=3
    )
    img = sim.image.copy()
    img[round(v0 + 0.3 * (v1 - v0)) :, :] = 90
    with pytest.raises(PlateNotFound) as exc:
        detect_plate(img, SPEC, "few.png")
    words = str(exc.value)
    assert "few.png" in words and f"needs at least {MIN_SEEN} corners in 2 or more rows and columns" in words
    assert "9 unknowns" in words and "leave 14 to judge the fit" in words and "of its 54 corners" in words
    n = int(words.split("saw ")[1].split(" of")[0])
    assert n < MIN_SEEN and len(exc.value.seen_px) == n
    with pytest.raises(InputError, match=f"saw {n} of its 54 corners"):
        calibrate_plate(
            [img], SPEC, touches_from_text(sim.touches_csv, "t.csv", ["few.png"]), names=["few.png"]
        )


def test_record_built_from_detected_ids_and_reused_after_a_bump(partial):
    """touches_again on a board seen in part: the touches move by id; a touched corner not seen in
    the new image is refused naming it."""
    how, sim, det = partial
    touches = touches_from_text(sim.touches_csv, "touches.csv", ["plate.png"])
    found = [PlateImage("plate.png", det.image_size, det.uv_px)]
    cal = calibrate_plate([sim.image], SPEC, touches, names=["plate.png"])
    again, note = touches_again(cal, det.spec, found)
    assert "moved 0.00 px" in note and [t.uv_px for t in again] == [
        tuple(det.uv_px[c]) for c in cal.plate.placements[0].corners
    ]
    lost = det.uv_px.copy()
    c0 = cal.plate.placements[0].corners[0]
    lost[c0] = np.nan
    with pytest.raises(InputError, match=f"corner {det.spec.ids()[c0]} is not seen in the new image"):
        touches_again(cal, det.spec, [PlateImage("plate.png", det.image_size, lost)])


def test_a_whole_board_writes_no_ids():
    """Every earlier plate file (a whole board) keeps its fields: ids only for a board seen in part."""
    spec = PlateSpec.parse(SPEC)
    uv = np.arange(108, dtype=float).reshape(54, 2)
    whole = PlateImage("p.png", (2448, 2048), uv)
    assert "ids" not in whole.to_dict(spec)
    assert np.array_equal(PlateImage.from_dict(whole.to_dict(spec), spec, 0).uv_px, uv)
    part = uv.copy()
    part[[3, 7]] = np.nan
    d = PlateImage("p.png", (2448, 2048), part).to_dict(spec)
    assert len(d["uv_px"]) == 52 and "r0c3" not in d["ids"] and d["ids"][:3] == ["r0c0", "r0c1", "r0c2"]
    back = PlateImage.from_dict(d, spec, 0).uv_px
    assert np.array_equal(np.isnan(back), np.isnan(part)) and np.array_equal(
        back[~np.isnan(back)], part[~np.isnan(part)]
    )


def test_the_cli_calibrates_a_partial_board_and_refuses_too_few(tmp_path):
    """As a user runs it (a real process): the partial board annotated and calibrated (exit 0); a crop
    with too few corners refused in one error line with the library's words (exit 2)."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    from eyetohand.sim import write_plate_simulation

    sim = simulate_plate(spec=SPEC, seed=3, touch_noise_mm=0.05, shift_mm=(100.0, 0.0))
    write_plate_simulation(sim, tmp_path)
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1] / "src"))

    def run(*args):
        cmd = [sys.executable, "-m", "eyetohand.cli", *args]
        return subprocess.run(cmd, capture_output=True, text=True, cwd=tmp_path, env=env, timeout=300)

    r = run(
        "calibrate-plate",
        "plate.png",
        "--plate",
        SPEC,
        "--touches",
        "touches.csv",
        "--check",
        "check.csv",
        "--annotate",
        "ann.png",
        "-o",
        "cal.json",
    )
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "ann.png").stat().st_size > 0
    assert len(Calibration.load(tmp_path / "cal.json").plate.images[0].to_dict(sim.spec)["ids"]) >= MIN_SEEN
    import cv2

    cv2.imwrite(str(tmp_path / "few.png"), sim.image[:1000, :1100])
    r = run("calibrate-plate", "few.png", "--plate", SPEC, "--touches", "touches.csv", "-o", "few.json")
    assert r.returncode == 2 and r.stderr.count("\n") == 1, r.stderr
    assert f"needs at least {MIN_SEEN} corners in 2 or more rows and columns" in r.stderr
    assert not (tmp_path / "few.json").exists()


def test_http_calibrates_a_partial_board_and_refuses_too_few_in_the_same_words(tmp_path, partial):
    """POST /api/plate/calibrate (a real app in-process): a partial board answered with a file that proves
    itself and keeps the ids; too few corners 422 naming images[0] in the library's words."""
    import base64

    import cv2
    from fastapi.testclient import TestClient

    from eyetohand.server.app import create_app

    how, sim, det = partial

    def body(img) -> dict:
        png = cv2.imencode(".png", img)[1].tobytes()
        return {
            "plate": SPEC,
            "images": [{"name": "plate.png", "data_base64": base64.b64encode(png).decode()}],
            "touches": {
                "name": "touches.csv",
                "data_base64": base64.b64encode(sim.touches_csv.encode()).decode(),
            },
        }

    with TestClient(create_app(tmp_path / "data")) as c:
        r = c.post("/api/plate/calibrate", json=body(sim.image))
        assert r.status_code == 200, r.text
        cal = Calibration.from_dict(r.json()["calibration"], "answer")
        assert cal.plate is not None and np.array_equal(cal.plate.images[0].seen, det.seen)
        r = c.post("/api/plate/calibrate", json=body(np.ascontiguousarray(sim.image[:1000, :800])))
        assert r.status_code == 422 and r.json()["field"] == "images[0]", r.text
        assert f"needs at least {MIN_SEEN} corners in 2 or more rows and columns" in r.json()["error"]


def test_simulate_makes_a_board_seen_in_part_from_the_command_line(tmp_path, board_px, capsys):
    """``eyetohand simulate --plate SPEC --plate-cover U0,V0,U1,V1`` / ``--plate-shift-mm DX,DY``: the
    library's cover and shift from the command line (the same touches as the library's session of that
    seed), calibrated by ``calibrate-plate``; a malformed value exits 2 with one line naming it."""
    from eyetohand.cli import main

    u0, v0, u1, v1 = _middle_third(board_px)
    cover = f"{u0:.1f},{v0:.1f},{u1:.1f},{v1:.1f}"
    for flags, kwargs in (
        (["--plate-cover", cover], {"cover_px": (round(u0, 1), v0, round(u1, 1), v1)}),
        (["--plate-shift-mm", "100,0"], {"shift_mm": (100.0, 0.0)}),
    ):
        out = tmp_path / flags[0].strip("-")
        args = [
            "simulate",
            "--plate",
            SPEC,
            *flags,
            "--seed",
            "3",
            "--touch-noise-mm",
            "0.05",
            "--out",
            str(out),
        ]
        assert main(args) == 0, capsys.readouterr().err
        lib = simulate_plate(spec=SPEC, seed=3, touch_noise_mm=0.05, render=False, **kwargs)
        assert (out / "touches.csv").read_text() == lib.touches_csv, flags
        code = main(
            [
                "calibrate-plate",
                str(out / "plate.png"),
                "--plate",
                SPEC,
                "--touches",
                str(out / "touches.csv"),
            ]
            + ["--check", str(out / "check.csv"), "-o", str(out / "cal.json")]
        )
        assert code == 0, capsys.readouterr().err
        assert (
            MIN_SEEN <= len(Calibration.load(out / "cal.json").plate.images[0].to_dict(lib.spec)["ids"]) < 54
        )
    capsys.readouterr()
    for flags, words in (
        (["--plate-cover", "1,2,3"], "--plate-cover: expected 4 comma-separated numbers"),
        (["--plate-cover", "900,10,500,20"], "plate cover: expected a rectangle u0,v0,u1,v1 px with u0 < u1"),
        (["--plate-shift-mm", "5,nan"], "--plate-shift-mm: 'nan' must be a finite number"),
        (["--plate-shift-mm", "5"], "--plate-shift-mm: expected 2 comma-separated numbers"),
    ):
        out = tmp_path / "bad"
        assert main(["simulate", "--plate", SPEC, *flags, "--out", str(out)]) == 2, flags
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and words in err, err
        assert not out.exists()
    assert main(["simulate", "--plate-cover", cover, "--out", str(tmp_path / "no")]) == 2
    assert "--plate-cover goes with --plate SPEC" in capsys.readouterr().err
