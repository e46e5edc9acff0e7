"""sigma_mm of a calibration from several plate placements (issue 37): each placement's rigid-fit
covariance moved through the map's own fit (PlateRecord.fitted), checked against a numerical
Jacobian through the fit — the placement's pairs moved rigidly, the model refitted — and kept on load."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from test_plate import two_placements

from eyetohand.calibration import Calibration, calibrate
from eyetohand.calibration.plate import calibrate_detected
from eyetohand.calibration.plate_record import PlateImage
from eyetohand.calibration.touches import touches_from_text
from eyetohand.core import PointPairs
from eyetohand.geometry import rodrigues_to_matrix
from eyetohand.sim import simulate_plate
from eyetohand.solve import param_jacobian

SPEC = "chessboard:9x6:12"


def test_each_placements_error_moves_the_map_as_a_refit_does(tmp_path):
    sims, cal = two_placements(touch_noise_mm=0.1)
    rec = cal.plate
    assert cal.model_name == "camera" and rec.response is not None and rec.response.shape[1] == 12
    uv = np.array([[1000.0, 900.0], [1400.0, 1150.0], [1224.0, 1024.0]])
    n0 = int(rec.images[0].seen.sum())
    for i, pl in enumerate(rec.placements):
        w, V = np.linalg.eigh(0.5 * (pl.covariance + pl.covariance.T))
        k = int(np.argmax(w))  # the placement's largest rigid error: its factor's column
        delta = V[:, k] * np.sqrt(w[k])  # (ω rad, t mm) about the touches' centre
        R = rodrigues_to_matrix(delta[:3])
        xyz = cal.pairs.xyz_mm.copy()
        part = slice(0, n0) if i == 0 else slice(n0, None)
        xyz[part] = (xyz[part] - pl.fit.centre_mm) @ R.T + pl.fit.centre_mm + delta[3:]
        moved = calibrate(PointPairs(cal.pairs.uv_px, xyz, cal.pairs.ids), "camera", image_size=(2448, 2048))
        for z in (0.0, 30.0, 60.0):
            zs = np.full(len(uv), z)
            refit = (
                moved.map(uv, zs, allow_outside=True).xyz_mm - cal.map(uv, zs, allow_outside=True).xyz_mm
            )[:, :2]
            J = param_jacobian(cal.model, uv, zs)[:, :2]
            predicted = J @ rec.response[:, 6 * i + k]
            # the linearised least squares against the refit: to a few % of the motion (~0.05 mm)
            assert np.abs(refit - predicted).max() < 0.05 * np.abs(refit).max() + 1e-4, (
                i,
                z,
                refit,
                predicted,
            )
    # sigma from the propagation, and the same after the file's round trip
    m = cal.map(uv, 30.0)
    old = replace(rec, response=None)  # the earlier approximation: the mean of the variances / K
    xyz = m.xyz_mm
    assert not np.allclose(rec.placement_variance_mm2(xyz, 2), old.placement_variance_mm2(xyz, 2), rtol=0.02)
    cal.save(tmp_path / "cal.json")
    again = Calibration.load(tmp_path / "cal.json")
    assert again.plate.response is not None
    assert np.array_equal(again.map(uv, 30.0).sigma_mm, m.sigma_mm)


def test_one_placement_keeps_its_rigid_error_as_it_is():
    sim = simulate_plate(spec=SPEC, seed=4, render=False, touch_noise_mm=0.1)
    found = [PlateImage("p.png", sim.camera.image_size, sim.true_uv_px)]
    cal = calibrate_detected(sim.spec, found, touches_from_text(sim.touches_csv, "t.csv", ["p.png"]))
    assert cal.plate.response is None and cal.plate.model is cal.model
