"""Tool-centre offset: the "9 + 2" practice on the simulator recovers the offset, and calibrating the
corrected pairs maps pixels to where objects really are."""

import numpy as np
import pytest

from eyetohand import InputError, calibrate, load_pairs
from eyetohand.calibration.fit import tcp_offset_for as estimate_tcp_offset
from eyetohand.cli import main
from eyetohand.sim.cell import Cell
from eyetohand.sim.simulate import simulate
from eyetohand.solve.tcp_offset import correct_pairs, has_turns, rotations


def calibrate_with_tcp(pairs, **options):
    cal = calibrate(pairs, **options)
    return cal, cal.tcp_offset


OFFSET = np.array([0.35, -0.2])
CELL = Cell.default().with_values(robot={"tcp_offset_mm": OFFSET.tolist()})


def test_rotation_convention_is_counter_clockwise():
    R = rotations(np.array([0.0, 90.0, 180.0]))
    np.testing.assert_allclose(R[1] @ [1.0, 0.0], [0.0, 1.0], atol=1e-15)
    np.testing.assert_allclose(R[2] @ [1.0, 0.0], [-1.0, 0.0], atol=1e-15)


def test_correct_pairs_moves_each_pair_to_its_tool_point():
    sim = simulate(CELL, "grid:3x3", (150.0,), n_check=0, angles_deg=(0.0, 90.0, 180.0), seed=0)
    fixed = correct_pairs(sim.pairs, OFFSET)
    d = fixed.xyz_mm[:, :2] - sim.pairs.xyz_mm[:, :2]
    np.testing.assert_allclose(d, (rotations(sim.pairs.angle_deg) @ OFFSET), atol=1e-12)
    assert fixed.angle_deg is None and any("tool-centre offset" in n for n in fixed.notes)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_nine_plus_two_recovers_the_offset_within_20_um(seed):
    sim = simulate(CELL, "grid:3x3", (150.0,), n_check=20, angles_deg=(0.0, 90.0, 180.0), seed=seed)
    assert len(sim.pairs) == 11 and has_turns(sim.pairs)
    est = estimate_tcp_offset(sim.pairs, image_size=CELL.image_size)
    err = np.linalg.norm(np.array(est.offset_mm) - OFFSET)
    print(
        f"seed {seed}: offset {est.offset_mm[0]:.4f}, {est.offset_mm[1]:.4f} mm "
        f"(± {est.std_mm[0]:.4f}), error {err:.4f} mm, model {est.model}"
    )
    assert err < 0.02
    assert est.n_turned == 2 and est.reference_angle_deg == 0.0


def test_calibration_with_the_offset_removed_finds_objects():
    sim = simulate(CELL, "grid:3x3", (150.0,), n_check=30, angles_deg=(0.0, 90.0, 180.0), seed=4)
    cal, tcp = calibrate_with_tcp(sim.pairs, check=sim.check, image_size=CELL.image_size, loo=False)
    # ignoring the offset: the classic 9 pairs at one tool angle
    one_angle = sim.pairs.subset(sim.pairs.angle_deg == 0.0)
    plain = calibrate(one_angle, check=sim.check, image_size=CELL.image_size, loo=False)
    assert plain.tcp_offset is None
    print(
        f"check rms: with offset removed {cal.check.rms_mm:.4f} mm, ignoring it {plain.check.rms_mm:.4f} mm"
    )
    assert tcp is not None
    assert cal.check.rms_mm < 0.03
    assert plain.check.rms_mm > 0.1  # the offset biases an uncorrected calibration
    assert any("tool-centre offset" in n for n in cal.notes)
    assert cal.tcp_offset is tcp


def test_pairs_at_one_angle_cannot_show_an_offset():
    sim = simulate(CELL, "grid:3x3", (150.0,), n_check=0, angles_deg=(0.0,), seed=0)
    assert sim.pairs.angle_deg is not None and not has_turns(sim.pairs)
    with pytest.raises(InputError, match="two or more tool angles"):
        estimate_tcp_offset(sim.pairs)
    cal, tcp = calibrate_with_tcp(sim.pairs, loo=False)
    assert tcp is None and cal.model_name


def test_simulate_cli_writes_the_angle_column(tmp_path, capsys):
    cfg = tmp_path / "cell.toml"
    cfg.write_text("[robot]\ntcp_offset_mm = [0.35, -0.2]\n")
    out = tmp_path / "sim"
    code = main(
        [
            "simulate",
            "--config",
            str(cfg),
            "--plan",
            "grid:3x3",
            "--angles",
            "0,90,180",
            "--out",
            str(out),
            "--seed",
            "5",
            "--check",
            "5",
        ]
    )
    assert code == 0, capsys.readouterr().err
    pairs = load_pairs(out / "pairs.csv")
    assert pairs.angle_deg is not None and sorted(set(pairs.angle_deg)) == [0.0, 90.0, 180.0]
    est = estimate_tcp_offset(pairs, image_size=(2448, 2048))
    assert np.linalg.norm(np.array(est.offset_mm) - OFFSET) < 0.02


def test_cli_calibrate_removes_the_offset_and_the_file_keeps_it(tmp_path, capsys):
    import json

    from eyetohand import Calibration
    from eyetohand.cli import main

    sim = simulate(CELL, "grid:3x3", (150.0,), n_check=0, angles_deg=(0.0, 90.0, 180.0), seed=4)
    src = tmp_path / "pairs.csv"
    src.write_text(sim.pairs.to_csv_text())
    out = tmp_path / "cal.json"
    assert main(["calibrate", str(src), "--json", "-o", str(out)]) == 0
    d = json.loads(capsys.readouterr().out)
    assert np.linalg.norm(np.array(d["tcp_offset"]["offset_mm"]) - OFFSET) < 0.02
    assert Calibration.load(out).tcp_offset.offset_mm == tuple(d["tcp_offset"]["offset_mm"])
