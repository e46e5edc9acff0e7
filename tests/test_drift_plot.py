"""The drift plot (issue 30 part 4): a calibration's checks over time against the limit, version changes
marked — ``reports.plot_drift``, the report's "Drift" section (``eyetohand report --history``), and the
trust map's camera background."""

from __future__ import annotations

import datetime as dt
import json

import matplotlib.dates as mdates
import numpy as np
import pytest
from helpers import PAPER

from eyetohand import InputError, calibrate, load_pairs
from eyetohand.cli import main
from eyetohand.reports import load_history, plot_drift, trust_map

ENTRIES = [  # out of order on purpose: the plot sorts by time
    {"utc": "2024-05-02T08:00:00+00:00", "max_mm": 0.08, "rms_mm": 0.04, "tolerance_mm": 0.2, "version": 1},
    {"utc": "2024-05-01T08:00:00+00:00", "max_mm": 0.05, "rms_mm": 0.03, "tolerance_mm": 0.2, "version": 1},
    {"utc": "2024-05-03T08:00:00.250+00:00", "error_mm": 0.12, "version": 1},  # a CAL CHECK
    {"utc": "2024-05-04T08:00:00+00:00", "max_mm": 0.25, "rms_mm": 0.15, "tolerance_mm": 0.2, "version": 1},
    {"utc": "2024-05-05T08:00:00+00:00", "max_mm": 0.04, "rms_mm": 0.02, "tolerance_mm": 0.2, "version": 2},
    {"utc": "2024-05-06T08:00:00+00:00", "error_mm": 0.06, "version": 2},
]


def _line(ax, gid):
    found = [ln for ln in ax.get_lines() if ln.get_gid() == gid]
    assert len(found) == 1, [ln.get_gid() for ln in ax.get_lines()]
    return found[0]


def _days(texts):
    return [mdates.date2num(dt.datetime.fromisoformat(t)) for t in texts]


def test_the_line_is_the_entries_and_the_limit_is_the_tolerance():
    ax = plot_drift(ENTRIES)
    ordered = sorted(ENTRIES, key=lambda e: e["utc"])
    line = _line(ax, "drift-error")
    x = mdates.date2num(line.get_xdata())
    np.testing.assert_allclose(x, _days([e["utc"] for e in ordered]), rtol=0, atol=1e-9)
    want = [e.get("max_mm", e.get("error_mm")) for e in ordered]
    np.testing.assert_array_equal(line.get_ydata(), want)
    limit = _line(ax, "limit")
    assert set(limit.get_ydata()) == {0.2}
    assert "limit 0.2 mm" in [t.get_text() for t in ax.get_legend().get_texts()]
    # one check beyond the limit, ringed and counted
    assert "beyond the limit (1)" in [t.get_text() for t in ax.get_legend().get_texts()]
    # the version change: a vertical line at the first check of version 2, labelled
    mark = _line(ax, "version-2")
    assert mdates.date2num(mark.get_xdata()[0]) == pytest.approx(_days([ordered[4]["utc"]])[0])
    assert " v2" in [t.get_text() for t in ax.texts]


def test_a_given_limit_and_the_versions_times():
    made = "2024-05-04T20:00:00+00:00"  # when version 2 was made, between two checks
    ax = plot_drift(ENTRIES, limit_mm=0.1, versions=[("2024-04-30T00:00:00+00:00", 1), (made, 2)])
    assert set(_line(ax, "limit").get_ydata()) == {0.1}
    texts = [t.get_text() for t in ax.get_legend().get_texts()]
    assert "beyond the limit (2)" in texts  # 0.12 and 0.25 mm
    # version 1 was made before the first check: not drawn; version 2 where it was made
    assert not [ln for ln in ax.get_lines() if ln.get_gid() == "version-1"]
    x = mdates.date2num(_line(ax, "version-2").get_xdata()[0])
    assert x == pytest.approx(_days([made])[0])


def test_a_tolerance_that_changed_is_a_step_and_no_tolerance_no_line():
    entries = [
        {"utc": "2024-05-01T08:00:00+00:00", "max_mm": 0.05, "tolerance_mm": 0.2},
        {"utc": "2024-05-02T08:00:00+00:00", "max_mm": 0.05, "tolerance_mm": 0.1},
    ]
    limit = _line(plot_drift(entries), "limit")
    assert list(limit.get_ydata()) == [0.2, 0.1, 0.1]
    checks_only = [{"utc": "2024-05-01T08:00:00+00:00", "error_mm": 0.05}]
    ax = plot_drift(checks_only)
    assert not [ln for ln in ax.get_lines() if ln.get_gid() == "limit"]
    np.testing.assert_array_equal(_line(ax, "drift-error").get_ydata(), [0.05])


def test_ax_convention():
    from matplotlib.figure import Figure

    fig = Figure()
    ax = fig.add_subplot()
    assert plot_drift(ENTRIES, ax, title=None) is ax
    assert ax.get_title() == ""


@pytest.mark.parametrize(
    ("entries", "words"),
    [
        ([], "no checks"),
        ([{"max_mm": 0.1}], "history entry 1: no 'utc'"),
        ([{"utc": "yesterday", "max_mm": 0.1}], "'utc' 'yesterday' is not an ISO 8601 time"),
        ([{"utc": "2024-05-01T08:00:00"}], "neither 'max_mm'"),
    ],
)
def test_bad_histories_are_named(entries, words):
    with pytest.raises(InputError, match=words):
        plot_drift(entries)


def test_load_history_skips_a_torn_last_line_only(tmp_path):
    p = tmp_path / "cal.json.history.jsonl"
    p.write_text(json.dumps(ENTRIES[0]) + "\n\n" + json.dumps(ENTRIES[1]) + '\n{"utc": "2024')
    assert load_history(p) == ENTRIES[:2]
    p.write_text('{"utc"\n' + json.dumps(ENTRIES[0]) + "\n")
    with pytest.raises(InputError, match="line 1: not JSON"):
        load_history(p)
    p.write_text("[1, 2]\n")
    with pytest.raises(InputError, match="line 1: not a JSON object"):
        load_history(p)


def test_report_has_a_drift_section_with_history(tmp_path, capsys):
    cal = calibrate(load_pairs(PAPER / "calibration_points.csv"), "homography", "lm", loo=False)
    cal_path = tmp_path / "cal.json"
    cal.save(cal_path)
    hist = tmp_path / "cell.checks.jsonl"
    hist.write_text("".join(json.dumps(e) + "\n" for e in ENTRIES))
    out = tmp_path / "report"
    assert main(["report", str(cal_path), "--history", str(hist), "--limit", "0.3", "-o", str(out)]) == 0
    html = (out / "index.html").read_text(encoding="utf-8")
    assert 'id="drift"' in html and "of the 6 checks over time" in html
    assert "the worst was 0.2500 mm on 2024-05-04 08:00 UTC" in html
    assert (out / "drift.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # without --history: no drift section
    out2 = tmp_path / "plain"
    assert main(["report", str(cal_path), "-o", str(out2)]) == 0
    assert 'id="drift"' not in (out2 / "index.html").read_text(encoding="utf-8")
    assert not (out2 / "drift.png").exists()
    # a bad --limit is the CLI's error, exit 2
    assert main(["report", str(cal_path), "--history", str(hist), "--limit", "-1", "-o", str(out)]) == 2
    assert "limit_mm must be a positive number" in capsys.readouterr().err


def test_trust_map_background_must_be_the_calibrations_image_size():
    cal = calibrate(load_pairs(PAPER / "calibration_points.csv"), "homography", "lm", loo=False)
    hull = cal.region.hull_px
    w, h = int(hull[:, 0].max() + 100), int(hull[:, 1].max() + 100)
    ax, _ = trust_map(cal, background=np.zeros((h, w), np.uint8))
    assert len(ax.images) == 1 and ax.images[0].get_array().shape == (h, w)
    assert ax.get_xlim() == (-0.5, w - 0.5)
    sized = calibrate(
        load_pairs(PAPER / "calibration_points.csv"), "homography", "lm", loo=False, image_size=(w + 1, h)
    )
    assert sized.image_size == (w + 1, h)
    with pytest.raises(InputError, match="background: the image is"):
        trust_map(sized, background=np.zeros((h, w), np.uint8))
