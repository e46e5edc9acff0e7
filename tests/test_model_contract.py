"""The model contract, checked on every registered model: what any code outside ``models/`` may rely
on, so that a new model is tested the moment it is registered."""

import ast
import json
from pathlib import Path

import numpy as np
import pytest
from synth import grid_pairs, make_camera, random_pairs

from eyetohand import InputError
from eyetohand.calibration.fit import fit_model
from eyetohand.models import MODELS, HeightRule, Model, RobotToImage, model_from_dict

SRC = Path(__file__).resolve().parents[1] / "src" / "eyetohand"
ALL = list(MODELS)


def heights_for(cls) -> tuple[float, ...]:
    return (150.0, 200.0) if cls.needs_heights() else (150.0,)


def fitted(name, optimizer="lm", noise_px=0.3, dist=(-0.1, 0.0, 0, 0, 0), tilt_deg=10.0):
    cam = make_camera(tilt_deg=tilt_deg, dist=list(dist))
    pairs = grid_pairs(cam, 5, heights=heights_for(MODELS[name]), noise_px=noise_px)
    model, _ = fit_model(pairs, name, optimizer)
    return model, pairs


def z_of(model, pairs):
    return None if model.height_rule is HeightRule.COMPUTED else pairs.xyz_mm[:, 2]


@pytest.mark.parametrize("name", ALL)
def test_declares_the_contract(name):
    cls = MODELS[name]
    assert issubclass(cls, Model) and cls.name == name
    assert cls.n_params > 0 and cls.min_pairs > 0 and cls.summary
    assert isinstance(cls.height_rule, HeightRule) and isinstance(cls.auto_candidate, bool)
    assert cls.n_unknowns() >= cls.n_params or cls.unknowns == 0
    for method in ("from_pairs", "batch_image_to_robot", "robot_to_image"):
        assert method not in getattr(cls, "__abstractmethods__", ()), method


@pytest.mark.parametrize("name", ALL)
def test_save_load_is_bit_identical_and_keeps_constants_apart(name):
    model, pairs = fitted(name)
    d = json.loads(json.dumps(model.to_dict(), allow_nan=False))
    assert set(d) == {"name", "params", "constants", "diagnostics"}
    cls = MODELS[name]
    assert (
        set(cls.constant_shapes)
        <= set(d["constants"])
        <= {*cls.constant_shapes, *cls.optional_constant_shapes}
    )
    back = model_from_dict(d)
    z = z_of(model, pairs)
    assert np.array_equal(back.image_to_robot(pairs.uv_px, z), model.image_to_robot(pairs.uv_px, z))
    # diagnostics never change a mapping
    d2 = dict(d, diagnostics={})
    assert np.array_equal(
        model_from_dict(d2).image_to_robot(pairs.uv_px, z), model.image_to_robot(pairs.uv_px, z)
    )
    # the pre-0.2 form (one merged 'meta') still loads to the same mapping
    legacy = {"name": d["name"], "params": d["params"], "meta": {**d["diagnostics"], **d["constants"]}}
    assert np.array_equal(
        model_from_dict(legacy).image_to_robot(pairs.uv_px, z), model.image_to_robot(pairs.uv_px, z)
    )


@pytest.mark.parametrize("name", [n for n in ALL if MODELS[n].constant_shapes])
def test_a_missing_or_misshapen_constant_is_refused_by_name(name):
    model, _ = fitted(name, "linear")
    d = model.to_dict()
    key = next(iter(d["constants"]))
    gone = dict(d, constants={k: v for k, v in d["constants"].items() if k != key})
    with pytest.raises(InputError, match=f"constant '{key}' missing"):
        model_from_dict(gone)
    bad = dict(d, constants={**d["constants"], key: [1.0, 2.0, 3.0, 4.0, 5.0]})
    with pytest.raises(InputError, match=f"constant '{key}'"):
        model_from_dict(bad)
    nan = dict(d, params=[float("nan")] + d["params"][1:])
    with pytest.raises(InputError, match="finite"):
        model_from_dict(nan)


@pytest.mark.parametrize("name", ALL)
def test_inverse_is_a_transform_and_undoes_the_forward_map(name):
    model, pairs = fitted(name)
    xyz = model.image_to_robot(pairs.uv_px, z_of(model, pairs))
    inv = model.inverse
    assert isinstance(inv, RobotToImage) and inv.inverse is model
    np.testing.assert_allclose(inv(xyz), pairs.uv_px, atol=1e-7)
    np.testing.assert_allclose(inv.residuals(xyz, pairs.uv_px), 0.0, atol=1e-7)


@pytest.mark.parametrize("name", ALL)
def test_batch_forward_equals_single(name):
    model, pairs = fitted(name, "linear")
    rng = np.random.default_rng(0)
    batch = model.params + 1e-4 * np.abs(model.params) * rng.normal(size=(7, model.n_params))
    out = model.batch_image_to_robot(batch, pairs.uv_px, pairs.xyz_mm[:, 2])
    for i in (0, 6):
        single = model.with_params(batch[i]).image_to_robot(pairs.uv_px, z_of(model, pairs))
        np.testing.assert_allclose(out[i], single, rtol=0, atol=1e-9)
    assert model.with_params(batch[3]).constants == model.constants


@pytest.mark.parametrize("name", ALL)
def test_one_point_equals_its_row_of_many(name):
    """The one-point paths (plain floats, no batch machinery) answer what the many-point path
    answers for that point, to rounding: the planar models take the precomputed px -> mm matrix,
    the lens models undistort a few points each to its own Newton stop (many points stop together)."""
    model, pairs = fitted(name)
    z = z_of(model, pairs)
    many = model.image_to_robot(pairs.uv_px, z)
    for i in range(len(pairs)):
        zi = None if z is None else float(np.asarray(z)[i])
        one = model.image_to_robot(pairs.uv_px[i], zi)
        assert one.shape == (1, 3)
        np.testing.assert_allclose(one[0], many[i], rtol=0, atol=1e-9)


@pytest.mark.parametrize("name", ALL)
def test_recovers_a_known_camera_from_noise_free_pairs(name):
    """Ground truth: a camera that every model can represent exactly (looking straight down, no lens,
    which is affine on each plane) — noise-free pairs must give the truth back on fresh points."""
    cls = MODELS[name]
    cam = make_camera(tilt_deg=0.0, dist=[0, 0, 0, 0, 0])
    pairs = grid_pairs(cam, 6, heights=heights_for(cls), noise_px=0.0, jitter_mm=2.0)
    fresh = random_pairs(cam, 30, heights=heights_for(cls), span_mm=90.0, seed=7)
    model, _ = fit_model(pairs, name, "lm")
    err = np.linalg.norm(model.residuals(fresh.uv_px, fresh.xyz_mm), axis=1)
    assert err.max() < 1e-4, f"{name}: {err.max():.2e} mm"


@pytest.mark.parametrize("name", ALL)
def test_height_rule_is_what_image_to_robot_does(name):
    model, pairs = fitted(name, "linear")
    uv = pairs.uv_px[:3]
    if model.height_rule is HeightRule.GIVEN:
        with pytest.raises(InputError, match="give z"):
            model.image_to_robot(uv)
        a, b = model.image_to_robot(uv, 150.0), model.image_to_robot(uv, 200.0)
        assert np.abs(a[:, :2] - b[:, :2]).max() > 1e-3 and np.all(b[:, 2] == 200.0)
    elif model.height_rule is HeightRule.PLANE:
        out = model.image_to_robot(uv)
        assert model.plane_z_mm == pytest.approx(150.0) and np.all(out[:, 2] == model.plane_z_mm)
    else:
        np.testing.assert_array_equal(model.image_to_robot(uv, 0.0), model.image_to_robot(uv, 500.0))
        assert model.plane_z_mm is None


def test_no_code_outside_models_special_cases_a_model_by_name():
    """A comparison with a model's name (``== "paper"``, ``in ("paper", ...)``) outside models/ is a
    rule that belongs in the model's class attributes."""
    names = set(MODELS)
    found = []
    for path in SRC.rglob("*.py"):
        if "models" in path.relative_to(SRC).parts:
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Compare):
                consts = [c for c in [node.left, *node.comparators] if isinstance(c, ast.Constant)]
                consts += [
                    e
                    for c in node.comparators
                    if isinstance(c, (ast.Tuple, ast.List, ast.Set))
                    for e in c.elts
                    if isinstance(e, ast.Constant)
                ]
                hit = [c.value for c in consts if c.value in names]
                if hit:
                    found.append(f"{path.relative_to(SRC)}:{node.lineno} compares with {hit}")
    assert not found, "\n".join(found)
