"""``eyetohand detect`` and ``eyetohand calibrate-images``: output, refusals, and calibration from
rendered images against what a user assembles from OpenCV."""

import csv
import json
import re
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from helpers import opencv_single_view_xy

from eyetohand.cli import main

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

from test_detect import REFUSALS, canvas, disc, finish  # noqa: E402


def run(capsys, *argv):
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def one_error_line(err: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and "Traceback" not in err, err
    return lines[0]


@pytest.fixture()
def target_png(tmp_path):
    path = tmp_path / "target.png"
    cv2.imwrite(str(path), finish(disc(canvas(), 300.3, 200.7, 30, 30)))
    return path


# ---------------------------------------------------------------- detect


def test_detect_prints_the_centre_and_json(target_png, tmp_path, capsys):
    code, out, err = run(capsys, "detect", target_png)
    assert code == 0 and err == ""
    m = re.fullmatch(rf"{re.escape(str(target_png))}: u (\S+) v (\S+) px  diameter \S+ px  score \S+\n", out)
    assert m and abs(float(m[1]) - 300.3) < 0.05 and abs(float(m[2]) - 200.7) < 0.05, out
    code, out, _ = run(capsys, "detect", target_png, "--json", "--annotate", tmp_path / "ann")
    assert code == 0
    res = json.loads(out)["results"][0]
    assert res["image"] == str(target_png) and res["ok"]
    assert abs(res["u"] - 300.3) < 0.05 and abs(res["v"] - 200.7) < 0.05
    assert abs(res["diameter_px"] - 60) < 0.5 and 0 < res["score"] <= 1
    ann = cv2.imread(str(tmp_path / "ann" / "target.annotated.png"))
    assert ann.shape == (480, 640, 3) and ((ann[:, :, 1] > 200) & (ann[:, :, 2] < 100)).sum() > 100


@pytest.mark.parametrize("case", REFUSALS)
def test_detect_refuses_images_without_one_clear_target(case, tmp_path, capsys):
    make, words = REFUSALS[case]
    path = tmp_path / "img.png"
    cv2.imwrite(str(path), make())
    code, out, err = run(capsys, "detect", path)
    assert code == 2 and out == ""
    line = one_error_line(err)
    assert str(path) in line and words in line


def _bad_files(tmp_path):
    ok, png = cv2.imencode(".png", finish(disc(canvas(), 300, 200, 30, 30)))
    (tmp_path / "trunc.png").write_bytes(png.tobytes()[: len(png) // 2])
    (tmp_path / "text.png").write_text("hello\n")
    cv2.imwrite(str(tmp_path / "tiny.png"), np.full((1, 1), 128, np.uint8))
    return {
        "trunc.png": "truncated PNG",
        "text.png": "not an image",
        "tiny.png": "1x1 px",
        "missing.png": "no such file",
    }


def test_detect_refuses_unreadable_files(tmp_path, capsys):
    for name, words in _bad_files(tmp_path).items():
        code, out, err = run(capsys, "detect", tmp_path / name)
        assert code == 2 and out == "", name
        line = one_error_line(err)
        assert str(tmp_path / name) in line and words in line


def test_detect_batch_lists_failures_and_exits_2(target_png, tmp_path, capsys):
    _bad_files(tmp_path)
    blank = tmp_path / "blank.png"
    cv2.imwrite(str(blank), np.full((100, 100), 90, np.uint8))
    code, out, err = run(capsys, "detect", target_png, blank, tmp_path / "text.png")
    assert code == 2
    lines = out.strip().splitlines()
    assert len(lines) == 3 and "u 300.3" in lines[0]
    assert "FAILED" in lines[1] and "no contrast" in lines[1] and "not an image" in lines[2]
    assert "2 of 3" in one_error_line(err)
    code, out, _ = run(capsys, "detect", target_png, blank, "--json")
    d = json.loads(out)
    assert code == 2 and d["failed"] == 1 and [r["ok"] for r in d["results"]] == [True, False]
    assert d["results"][1]["u"] is None
    code, _, _ = run(capsys, "detect", target_png, target_png)
    assert code == 0


# ---------------------------------------------------------------- calibrate-images

CELL = """[camera]
width_px = 816
height_px = 683
pixel_size_um = 10.35
principal_offset_px = [4.0, -3.0]
"""
W, H = 816, 683


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    """25 calibration + 20 check images at z = 150 mm from the default cell's tilted camera with lens
    distortion, at a third of its resolution (816×683, 10.35 µm pixels: the same view, target ~26 px)."""
    d = tmp_path_factory.mktemp("session")
    (d / "cell.toml").write_text(CELL)
    code = main(
        [
            "simulate",
            "--config",
            str(d / "cell.toml"),
            "--plan",
            "grid:5x5",
            "--heights",
            "150",
            "--check",
            "20",
            "--out",
            str(d / "sim"),
            "--seed",
            "3",
            "--images",
        ]
    )
    assert code == 0
    return d / "sim"


def _opencv_reference(folder):
    """What a user assembles from OpenCV: SimpleBlobDetector centres, a single-view calibrateCamera
    (principal point fixed at the image centre, square pixels, k1 k2 only), undistortPoints, then a
    homography to the robot's x, y; returns the check RMS (mm)."""
    from bench_detect import blob_detector

    sbd = blob_detector(min_area_px=150)

    def centres(name):
        uv, xy = [], []
        for r in csv.DictReader((folder / name).open()):
            kp = sbd.detect(cv2.imread(str(folder / r["image"]), cv2.IMREAD_GRAYSCALE))
            assert len(kp) == 1
            uv.append(kp[0].pt)
            xy.append([float(r["x"]), float(r["y"])])
        return np.array(uv), np.array(xy)

    uv, xy = centres("poses.csv")
    cuv, cxy = centres("check_poses.csv")
    pred = opencv_single_view_xy(uv, xy, (W, H), focal_px=W)(cuv)
    return float(np.sqrt(np.mean(np.sum((pred - cxy) ** 2, axis=1))))


def test_calibrate_images_matches_an_opencv_pipeline(session, capsys):
    code, out, err = run(
        capsys,
        "calibrate-images",
        session / "poses.csv",
        "--check",
        session / "check_poses.csv",
        "--model",
        "auto",
        "--image-size",
        f"{W}x{H}",
        "--json",
    )
    assert code == 0, err
    d = json.loads(out)
    assert d["train"]["n"] == 25 and d["check"]["n"] == 20
    assert d["left_out"] == [] and d["check_left_out"] == []
    assert len(d["detections"]) == 25 and all(r["ok"] for r in d["detections"])
    ref = _opencv_reference(session)
    print(
        f"calibrate-images --model auto: {d['model']}, check rms {d['check']['rms_mm']:.4f} mm; "
        f"OpenCV (SimpleBlobDetector + calibrateCamera + homography) {ref:.4f} mm"
    )
    assert d["check"]["rms_mm"] <= 1.5 * ref


def test_calibrate_images_leaves_out_failed_images_and_says_so(session, tmp_path, capsys):
    rows = list(csv.DictReader((session / "poses.csv").open()))[:12]
    cv2.imwrite(str(tmp_path / "blank.png"), np.full((H, W), 90, np.uint8))
    (tmp_path / "text.png").write_text("hello\n")
    with (tmp_path / "poses.csv").open("w") as fh:
        fh.write("image,x,y,z\n")
        for r in rows:
            fh.write(f"{session / r['image']},{r['x']},{r['y']},{r['z']}\n")
        fh.write(f"blank.png,{rows[0]['x']},{rows[1]['y']},150\n")
        fh.write("text.png,1,2,150\n")
    code, out, err = run(
        capsys, "calibrate-images", tmp_path / "poses.csv", "--model", "homography", "--json"
    )
    assert code == 0, err
    d = json.loads(out)
    assert d["left_out"] == ["blank.png", "text.png"] and d["train"]["n"] == 12
    assert "left out blank.png" in err and "left out text.png" in err
    ids = {p["id"] for p in d["train"]["points"]}
    assert "blank.png" not in ids and len(ids) == 12


def test_calibrate_images_input_errors(tmp_path, capsys):
    (tmp_path / "p.csv").write_text("image,x\na.png,1\n")
    code, _, err = run(capsys, "calibrate-images", tmp_path / "p.csv")
    assert code == 2 and "missing column(s) y" in one_error_line(err)
    (tmp_path / "q.csv").write_text("image,x,y\na.png,1,2\na.png,3,4\n")
    code, _, err = run(capsys, "calibrate-images", tmp_path / "q.csv")
    assert code == 2 and "listed twice" in one_error_line(err)
    (tmp_path / "r.csv").write_text("image,x,y\na.png,1,2\n")
    code, _, err = run(capsys, "calibrate-images", tmp_path / "r.csv")
    progress = [ln for ln in err.splitlines() if ln.startswith("detect")]  # not a terminal: a line per image
    assert progress == ["detecting 1/1: a.png", "detected 1 images"], err
    rest = "\n".join(ln for ln in err.splitlines() if not ln.startswith(("detect", "note: left out")))
    assert code == 2 and "found in none" in one_error_line(rest)


def test_calibrate_images_reports_progress_saves_pairs_and_annotated_images(session, tmp_path, capsys):
    rows = list(csv.DictReader((session / "poses.csv").open()))[:9]
    with (tmp_path / "poses.csv").open("w") as fh:
        fh.write("image,x,y,z\n")
        for r in rows:
            fh.write(f"{session / r['image']},{r['x']},{r['y']},{r['z']}\n")
    pairs_out, ann = tmp_path / "pairs.csv", tmp_path / "ann"
    code, out, err = run(
        capsys,
        "calibrate-images",
        tmp_path / "poses.csv",
        "--model",
        "homography",
        "--pairs-out",
        pairs_out,
        "--annotate",
        ann,
        "--json",
    )
    assert code == 0, err
    d = json.loads(out)
    lines = err.splitlines()
    # capsys' stderr is no terminal: one line per image, in order, then the end
    assert [ln for ln in lines if ln.startswith("detecting ")] == [
        f"detecting {i}/9: {session / r['image']}" for i, r in enumerate(rows, 1)
    ]
    assert "detected 9 images" in lines and f"wrote {pairs_out}: 9 detected pairs" in lines
    # the CSV calibrates to the same figures with `eyetohand calibrate`
    code, out2, err2 = run(capsys, "calibrate", pairs_out, "--model", "homography", "--json")
    assert code == 0, err2
    d2 = json.loads(out2)
    assert abs(d2["train"]["rms_mm"] - d["train"]["rms_mm"]) < 1e-9
    assert [p["id"] for p in d2["train"]["points"]] == [str(session / r["image"]) for r in rows]
    # one annotated picture per image, the ellipse drawn (green) and the centre written (yellow)
    pics = sorted(ann.glob("*.annotated.png"))
    assert len(pics) == 9
    img = cv2.imread(str(pics[0]))
    green = (img[:, :, 1] > 200) & (img[:, :, 2] < 100) & (img[:, :, 0] < 100)
    yellow = (img[:, :, 1] > 200) & (img[:, :, 2] > 200) & (img[:, :, 0] < 100)
    assert green.sum() > 30 and yellow.sum() > 50, (green.sum(), yellow.sum())


def test_calibrate_images_refuses_a_file_as_annotate_folder(tmp_path, capsys):
    (tmp_path / "p.csv").write_text("image,x,y\na.png,1,2\n")
    (tmp_path / "f").write_text("x")
    code, _, err = run(capsys, "calibrate-images", tmp_path / "p.csv", "--annotate", tmp_path / "f")
    assert code == 2 and "is not a folder" in one_error_line(err)


def test_per_point_table_aligns_long_ids(tmp_path, capsys):
    long_ids = [f"images/session-2024-05-17/pose_{i:03d}.png" for i in range(9)]
    src = (Path(__file__).resolve().parents[1] / "examples" / "paper" / "check_points.csv").read_text()
    rows = list(csv.DictReader(src.splitlines()))
    with (tmp_path / "c.csv").open("w") as fh:
        fh.write("id,u,v,x,y,z\n")
        for i, r in zip(long_ids, rows, strict=True):
            fh.write(f"{i},{r['u']},{r['v']},{r['x']},{r['y']},{r['z']}\n")
    train = Path(__file__).resolve().parents[1] / "examples" / "paper" / "calibration_points.csv"
    code, out, err = run(capsys, "calibrate", train, "--check", tmp_path / "c.csv", "--model", "homography")
    assert code == 0, err
    lines = out.splitlines()
    head = next(k for k, ln in enumerate(lines) if ln.split()[:2] == ["id", "dx_mm"])
    table = lines[head : head + 10]
    assert all(len(ln.removesuffix("  outlier")) == len(table[0]) for ln in table), "\n".join(table)
    assert all(ln.split()[0] in long_ids for ln in table[1:])
