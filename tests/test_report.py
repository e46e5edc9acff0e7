"""Reports and plots: HTML + PNGs on the paper data, the report CLI, atomicity, the demo report."""

import re

import numpy as np
import pytest

from eyetohand import InputError, calibrate
from eyetohand.cli import main
from eyetohand.reports import plots, report
from eyetohand.reports.report import write_report

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def assert_png(path, min_bytes=5000):
    data = path.read_bytes()
    assert data[:8] == PNG_SIGNATURE, path
    assert len(data) > min_bytes, (path, len(data))


@pytest.fixture(scope="module")
def paper_cal():
    from conftest import PAPER

    from eyetohand import load_pairs

    train = load_pairs(PAPER / "calibration_points.csv")
    check = load_pairs(PAPER / "check_points.csv")
    return calibrate(train, "homography", "lm", check=check), train, check


@pytest.fixture()
def cal_file(tmp_path, paper_cal):
    cal, _, _ = paper_cal
    return cal.save(tmp_path / "cal.json")


def snapshot(folder):
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


# ------------------------------------------------------------------ write_report


def test_write_report_on_paper_data(tmp_path, paper_cal):
    cal, train, check = paper_cal
    index = write_report(
        tmp_path / "r", cal, check_pairs=check, train_pairs=train, extra={"operator": "test"}
    )
    assert index == tmp_path / "r" / "index.html"
    text = index.read_text(encoding="utf-8")
    # the check RMS as the accuracy table prints it (4 decimals, mm)
    assert f"{cal.check.rms_mm:.4f}" == report.mm(cal.check.rms_mm)
    assert f'<td class="num">{cal.check.rms_mm:.4f}</td>' in text
    assert f"{cal.check.max_mm:.4f}" in text
    for name in ("check_errors.png", "train_errors.png", "residual_vectors.png", "sigma_map.png"):
        assert_png(tmp_path / "r" / name)
    # self-contained: images embedded, no external resources, no scripts
    assert text.count("data:image/png;base64,") == 4
    assert "Where this calibration can be trusted" in text
    assert not re.search(r"(src|href)=\"(https?:|//)", text)
    assert "<script" not in text
    assert "operator" in text and "homography" in text
    # per point table has every check id with its image position
    for pid, (u, v) in zip(check.ids, check.uv_px, strict=True):
        assert f"{u:.2f}" in text and f"{v:.2f}" in text, pid
    assert not list((tmp_path / "r").glob(".*.tmp"))


def test_report_draws_vectors_from_the_pairs_the_file_carries(tmp_path, paper_cal):
    """A calibration file stores its training and check pairs: the report draws them without --pairs
    (it once said the file did not store the image positions)."""
    cal, _, _ = paper_cal
    assert cal.pairs is not None and cal.check_pairs is not None
    text = write_report(tmp_path / "r", cal).read_text(encoding="utf-8")
    assert (tmp_path / "r" / "residual_vectors.png").exists()
    assert "not drawn" not in text and "but not its image position" not in text
    assert f"{cal.check.rms_mm:.4f}" in text  # the stored check stats are still reported


def test_report_without_pairs_skips_vectors_and_says_so(tmp_path, paper_cal):
    from dataclasses import replace

    cal, _, _ = paper_cal
    bare = replace(cal, pairs=None, check_pairs=None)
    text = write_report(tmp_path / "r", bare).read_text(encoding="utf-8")
    assert not (tmp_path / "r" / "residual_vectors.png").exists()
    assert "Residual vectors: not drawn" in text and "--pairs" in text


def test_report_with_pso_history_has_convergence_and_selection(tmp_path, paper_cal):
    from dataclasses import replace

    # the selection record of fit.select_model (made up here: the real one costs seconds)
    selection = {
        "chosen": "homography",
        "reason": "lowest held-out RMS (0.0308 mm)",
        "method": "leave-one-out",
        "candidates": [
            {"model": "affine", "unknowns": 6, "cv_rms_mm": 0.0321, "cv_max_mm": 0.07, "considered": True},
            {
                "model": "homography",
                "unknowns": 8,
                "cv_rms_mm": 0.0308,
                "cv_max_mm": 0.0667,
                "considered": True,
            },
            {
                "model": "homography-radial",
                "unknowns": 10,
                "cv_rms_mm": None,
                "considered": False,
                "why": "needs at least 9 pairs, have 8",
            },
        ],
    }
    cal = replace(paper_cal[0], selection=selection)
    text = write_report(tmp_path / "r", cal).read_text(encoding="utf-8")
    assert "auto selection chose" in text and "held-out RMS" in text and "needs at least 9 pairs" in text
    assert "No convergence plot" in text
    # a swarm history on the same calibration: the convergence plot appears
    cal2 = replace(cal, fit=replace(cal.fit, optimizer="hybrid-pso", history=(1.5, 0.4, 0.2, 0.1058)))
    write_report(tmp_path / "r", cal2)
    assert_png(tmp_path / "r" / "convergence.png")


def test_mismatched_train_pairs_are_flagged(tmp_path, paper_cal):
    cal, _, check = paper_cal
    text = write_report(tmp_path / "r", cal, train_pairs=check).read_text(encoding="utf-8")
    assert "not the data this calibration was fitted on" in text
    assert "given pairs" in text


def test_failed_run_leaves_earlier_report_intact(tmp_path, paper_cal, monkeypatch):
    cal, train, check = paper_cal
    out = tmp_path / "r"
    write_report(out, cal, check_pairs=check, train_pairs=train)
    before = snapshot(out)

    def boom(*args, **kwargs):
        raise RuntimeError("disk on fire")

    monkeypatch.setattr(plots, "plot_residual_vectors", boom)
    with pytest.raises(RuntimeError):
        write_report(out, cal, check_pairs=check, train_pairs=train)
    assert snapshot(out) == before


def test_output_path_that_is_a_file(tmp_path, paper_cal):
    cal, _, _ = paper_cal
    f = tmp_path / "file"
    f.write_text("x")
    with pytest.raises(InputError, match="not a folder"):
        write_report(f, cal)
    assert f.read_text() == "x"


# ------------------------------------------------------------------ plots


def new_ax():
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure()
    FigureCanvasAgg(fig)
    return fig.add_subplot()


def test_plots_draw_on_a_given_ax_and_label_units():
    ax = new_ax()
    assert plots.plot_convergence([3.0, 1.0, 0.5, 0.1], ax=ax) is ax
    assert "[mm]" in ax.get_ylabel()
    ax = new_ax()
    assert plots.plot_convergence({"hybrid": [2, 1, 0.1], "plain": [2, 1.5, 0.3, 0.2]}, ax=ax) is ax
    assert len(ax.get_lines()) == 2
    ax = new_ax()
    out = plots.plot_point_errors(
        {"a": [0.1, 0.2, None], "b": [0.05, 0.1, 0.02]},
        ["p1", "p2", "p3"],
        ax=ax,
        reference_lines={"limit": 0.0898},
    )
    assert out is ax and "[mm]" in ax.get_ylabel()
    assert [t.get_text() for t in ax.get_xticklabels()] == ["p1", "p2", "p3"]
    ax = new_ax()
    uv = np.array([[100.0, 200.0], [400.0, 50.0], [250.0, 300.0]])
    res = np.array([[0.01, -0.02, 0.0], [0.0, 0.03, 0.0], [-0.02, 0.0, 0.0]])
    assert plots.plot_residual_vectors(uv, res, ax=ax, image_size=(640, 480)) is ax
    assert ax.get_ylim() == (480, 0)  # v down
    assert "[px]" in ax.get_xlabel() and "[px]" in ax.get_ylabel()
    ax = new_ax()
    rows = [
        {"model": "homography", "optimizer": "lm", "check_rms_mm": 0.027, "check_max_mm": 0.056},
        {"model": "paper", "optimizer": "pso", "error": "unavailable"},
    ]
    assert plots.plot_model_comparison(rows, ax=ax) is ax
    assert "[mm]" in ax.get_xlabel()


def test_plots_create_their_own_figure_without_pyplot():
    ax = plots.plot_convergence([1.0, 0.5])
    assert ax.figure is not None
    import io

    buf = io.BytesIO()
    ax.figure.savefig(buf, format="png")
    assert buf.getvalue()[:8] == PNG_SIGNATURE


def test_plots_reject_bad_input():
    with pytest.raises(InputError):
        plots.plot_point_errors({"a": [0.1, 0.2], "b": [0.1]})
    with pytest.raises(InputError):
        plots.plot_convergence([])
    with pytest.raises(InputError):
        plots.plot_residual_vectors(np.zeros((3, 2)), np.zeros((2, 2)))


def test_nice_step():
    assert plots.nice_step(0.083) == pytest.approx(0.05)
    assert plots.nice_step(0.2) == pytest.approx(0.2)
    assert plots.nice_step(7.0) == pytest.approx(5.0)


# ------------------------------------------------------------------ CLI


def test_cli_report(tmp_path, cal_file, capsys):
    from conftest import PAPER

    out = tmp_path / "out"
    rc = main(
        [
            "report",
            str(cal_file),
            "--check",
            str(PAPER / "check_points.csv"),
            "--pairs",
            str(PAPER / "calibration_points.csv"),
            "-o",
            str(out),
        ]
    )
    assert rc == 0
    printed = capsys.readouterr().out.strip()
    assert printed == str(out / "index.html")
    assert (out / "index.html").is_file()
    assert_png(out / "residual_vectors.png")


def test_cli_report_bad_calibration_is_exit_2_and_writes_nothing(tmp_path, cal_file, capsys):
    bad = tmp_path / "bad.json"
    bad.write_text('{"schema": "something else"}')
    out = tmp_path / "new"
    assert main(["report", str(bad), "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error:")
    assert not out.exists()
    # an existing report is left as it was
    existing = tmp_path / "existing"
    assert main(["report", str(cal_file), "-o", str(existing)]) == 0
    before = snapshot(existing)
    capsys.readouterr()
    assert main(["report", str(bad), "-o", str(existing)]) == 2
    assert main(["report", str(cal_file), "--check", str(bad), "-o", str(existing)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and all(e.startswith("error:") for e in err)
    assert snapshot(existing) == before


def test_cli_report_needs_output(cal_file, capsys):
    assert main(["report", str(cal_file)]) == 2
    assert capsys.readouterr().err.startswith("error:")


def test_demo_out_writes_report_with_convergence(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out)]) == 0
    assert "report:" in capsys.readouterr().out
    text = (out / "index.html").read_text(encoding="utf-8")
    assert "Fig. 4" in text and "Fig. 5" in text and "convergence.png" in text
    assert_png(out / "convergence.png")
    assert_png(out / "point_errors.png")
    assert_png(out / "residual_vectors.png")
    assert "illegible" in text and "0.0898" in text
    assert "Table 3 published" in text


def test_many_points_label_only_the_largest_errors():
    rng = np.random.default_rng(0)
    uv = rng.uniform(0, 2000, (120, 2))
    res = rng.normal(0, 0.01, (120, 2))
    ax = plots.plot_residual_vectors(uv, res, ids=[f"p{i}" for i in range(120)], label_largest=5)
    worst = np.argsort(-np.linalg.norm(res, axis=1))[:5]
    assert sorted(t.get_text() for t in ax.texts) == sorted(f"p{i}" for i in worst)
    ax = plots.plot_point_errors({"a": np.abs(res[:, 0])})
    assert len(ax.get_xticklabels()) <= plots.MAX_TICK_LABELS


# ------------------------------------------------------------------ issue 16: plots a user reads


def _drawn(ax):
    ax.figure.canvas.draw()
    return ax.figure.canvas.get_renderer()


@pytest.mark.parametrize("n_methods", [1, 2, 3])
def test_legend_never_covers_a_bar(n_methods):
    rng = np.random.default_rng(n_methods)
    errs = {f"method {k}": rng.uniform(0.001, 0.05, 12) for k in range(n_methods)}
    errs["method 0"][-1] = 0.2  # the tallest bar under the upper-right legend
    ax = plots.plot_point_errors(errs, title="Error per training point")
    r = _drawn(ax)
    legend = ax.get_legend().get_window_extent(r)
    bars = [p.get_window_extent(r) for p in ax.patches]
    assert bars and not any(legend.overlaps(b) for b in bars)


def test_long_image_ids_do_not_overlap_on_the_axis():
    ids = [f"session-2024-05-17/images/pose_{i:03d}.png" for i in range(14)]
    ax = plots.plot_point_errors({"homography + lm": np.linspace(0.01, 0.05, 14)}, ids)
    r = _drawn(ax)
    boxes = [t.get_window_extent(r) for t in ax.get_xticklabels() if t.get_text()]
    assert [t.get_text() for t in ax.get_xticklabels()] == [f"pose_{i:03d}" for i in range(14)]
    assert all(not a.overlaps(b) for k, a in enumerate(boxes) for b in boxes[k + 1 :])


def test_a_users_report_does_not_cite_the_paper(tmp_path, paper_cal, monkeypatch):
    cal, train, check = paper_cal
    titles = []
    real = plots.plot_point_errors

    def spy(*a, **kw):
        ax = real(*a, **kw)
        titles.append(ax.get_title())
        return ax

    monkeypatch.setattr(plots, "plot_point_errors", spy)
    text = write_report(tmp_path / "r", cal, check_pairs=check, train_pairs=train).read_text(encoding="utf-8")
    assert "Error per check point" in titles and not any("paper" in t for t in titles), titles
    assert "paper's Fig" not in text


def test_demo_says_what_its_ranking_is_on(tmp_path, capsys):
    from eyetohand.reports.demo import run_demo, write_demo_report

    _, results, cals = run_demo(seed=1)
    text = write_demo_report(tmp_path / "d", results, cals).read_text(encoding="utf-8")
    assert "best here" not in text
    others = results["others"]
    by_rms = min(others, key=lambda k: others[k]["check_rms_mm"])
    assert f"lowest check RMS: {by_rms}" in text or "lowest check RMS: paper+" in text
    assert "ranks the fits on one figure, the RMS over the 9 check points" in text
    by_max = min(others, key=lambda k: others[k]["check_max_mm"])
    if by_max != by_rms:
        assert "Ranked on the check max instead" in text


def test_sigma_map_shows_sigma_over_the_image_with_the_region_outlined(paper_cal):
    cal, _, _ = paper_cal
    hull = cal.region.hull_px
    u = np.linspace(hull[:, 0].min() - 200, hull[:, 0].max() + 200, 40)
    v = np.linspace(hull[:, 1].min() - 200, hull[:, 1].max() + 200, 30)
    uv = np.column_stack([g.ravel() for g in np.meshgrid(u, v)])
    s = cal.uncertainty.sigma_mm(cal.model, uv, np.full(len(uv), cal.region.plane_z_mm)).reshape(30, 40)
    ax = plots.plot_sigma_map(u, v, s, hull, points_px=cal.pairs.uv_px)
    mesh = ax.collections[0]
    np.testing.assert_allclose(np.asarray(mesh.get_array()).reshape(30, 40), s)
    outline = ax.lines[0].get_xydata()
    np.testing.assert_allclose(outline[:-1], hull)
    np.testing.assert_allclose(outline[-1], hull[0])  # closed
    assert ax.get_ylim()[0] > ax.get_ylim()[1]  # v down
    assert "sigma_mm [mm]" in [a.get_ylabel() for a in ax.figure.axes]
    # the corners, far from the training points, have the largest sigma
    assert s[0, 0] > s[15, 20] and s[-1, -1] > s[15, 20]
    with pytest.raises(InputError, match="sigma_mm must have shape"):
        plots.plot_sigma_map(u, v, s.T, hull)


def test_sigma_map_legend_sits_under_the_map():
    """The sigma map's legend is drawn under the axes, never over the calibrated region's outline."""
    import numpy as np

    from eyetohand.reports.plots import plot_sigma_map

    u, v = np.arange(0, 800, 20.0), np.arange(0, 600, 20.0)
    hull = np.array([[40.0, 30.0], [760.0, 30.0], [760.0, 570.0], [40.0, 570.0]])
    ax = plot_sigma_map(u, v, np.ones((len(v), len(u))), hull, points_px=hull)
    fig = ax.figure
    fig.canvas.draw()
    legend = ax.get_legend().get_window_extent()
    assert legend.y1 < ax.get_window_extent().y0, (legend, ax.get_window_extent())
    assert [t.get_text() for t in ax.get_legend().get_texts()][0].startswith("calibrated region")
