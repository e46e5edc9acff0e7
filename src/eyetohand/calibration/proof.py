"""The proof of a calibration file: what :meth:`Calibration.from_dict
<eyetohand.calibration.Calibration.from_dict>` checks before it answers — every field typed and
shaped as this version writes it, the training pairs hashing to ``data_sha256``, the recorded
statistics reproduced (1e-9 mm), the derived fields (region, uncertainty, local frame) recomputed
and compared, the content's seal and signature — and the schema it checks against.
"""

from __future__ import annotations

import dataclasses
import json
from typing import TYPE_CHECKING

import numpy as np

from eyetohand._version import __version__
from eyetohand.calibration.fields import (
    CHANGED,
    KIND,
    MISSING,
    check_numbers,
    kind_of,
    rel_tol,
    same,
)
from eyetohand.calibration.points import FIELD as IMAGE_POINTS_FIELD
from eyetohand.calibration.signing import check_signature
from eyetohand.core import (
    FitInfo,
    InputError,
    PointPairs,
    Stats,
    TcpOffset,
    pairs_from_records,
    sha256_hex,
)
from eyetohand.geometry import CalibratedRegion, fit_height_plane
from eyetohand.models import HeightRule, Model, model_from_dict
from eyetohand.solve import Uncertainty, pair_leverage, stats_from_residuals

if TYPE_CHECKING:
    from eyetohand.calibration.file import Calibration

SCHEMA = "eyetohand.calibration"
SCHEMA_VERSION = 2
READS_VERSIONS = (2,)
"""Versions this eyetohand loads. Version 1 (eyetohand 0.1) is recognised only to be refused with its
reason: its files carry no pairs, so they cannot prove they are intact, and loading one without a
proof let an edited, relabelled and re-sealed version 2 file map unproven."""
V1_FIELDS = frozenset(
    "schema schema_version eyetohand_version created_utc units model plane_z_mm heights_mm image_size "
    "fit train check loo data_sha256 notes selection tcp_offset".split()
)
"""Every field a version 1 file has (eyetohand 0.1 wrote exactly these)."""
REPRODUCE_TOL_MM = 1e-9


def parse(
    cls: type[Calibration],
    d: dict,
    source: str = "<dict>",
    *,
    sign_key: bytes | None = None,
    require_signed: bool = False,
) -> Calibration:
    """``Calibration.from_dict``: ``d`` parsed and proven intact, or refused in one line naming the
    field (what is proven: the module docstring, and ``Calibration.from_dict``'s)."""
    if not isinstance(d, dict) or d.get("schema") != SCHEMA:
        raise InputError(f"{source}: not an eyetohand calibration file (no schema {SCHEMA!r})")
    ver = d.get("schema_version")
    if ver == 1 and not isinstance(ver, bool):
        raise InputError(f"{source}: {_v1_refusal(cls, d)}")
    if isinstance(ver, bool) or ver not in READS_VERSIONS:
        newer = isinstance(ver, int) and not isinstance(ver, bool) and ver > SCHEMA_VERSION
        raise InputError(
            f"{source}: calibration schema_version {ver!r}"
            + (
                f" is newer than this eyetohand {__version__} reads ({SCHEMA_VERSION}): upgrade eyetohand"
                if newer
                else f", this eyetohand reads {', '.join(map(str, READS_VERSIONS))}"
            )
        )
    try:
        check_signature(d, sign_key, require_signed)
        check_numbers(d, "")
        cal = _from_dict(cls, d, ver)
        cal = prove(cal, d)
    except InputError as exc:
        raise InputError(f"{source}: {_as_written(str(exc), d)}") from None
    except (KeyError, TypeError, ValueError, AttributeError, IndexError, OverflowError) as exc:
        raise InputError(f"{source}: {_malformed(exc)}") from None
    return cal


def prove(cal: Calibration, d: dict) -> Calibration:
    """``cal`` (parsed from ``d``) with its region and uncertainty recomputed from its pairs,
    after proving that ``d`` is what this calibration writes (see :func:`parse`)."""
    verify(cal)
    fitted = cal.fitted_pairs
    assert fitted is not None  # verify() refuses a file without pairs
    region = derived_region(cal.model, fitted)
    same(region.to_dict(), d.get("region", MISSING), "region", rel_tol(REPRODUCE_TOL_MM))
    unc = Uncertainty.of_fit(cal.model, fitted.uv_px, fitted.xyz_mm)
    _same_uncertainty(unc, d.get("uncertainty", MISSING), cal.model, fitted, region)
    out = dataclasses.replace(cal, region=region, uncertainty=unc)
    want = out.content()
    for key in FREE_FIELDS:
        want.pop(key, None)
    given = {k: v for k, v in d.items() if k not in FREE_FIELDS}
    want["model"] = dict(want["model"], diagnostics=given.get("model", {}).get("diagnostics"))
    want["uncertainty"] = given.get("uncertainty")  # compared above, with its own tolerance
    want["region"] = given.get("region")  # compared above
    if cal.plate is not None:
        want["plate"] = given.get("plate")  # proven when parsed (PlateRecord.from_dict)
    if IMAGE_POINTS_FIELD in want and IMAGE_POINTS_FIELD not in given:
        want.pop(IMAGE_POINTS_FIELD)  # written before the field: its fit record says the same (points.py)
    local = want.pop("local_frame")
    same(local, given.pop("local_frame", MISSING), "local_frame", rel_tol(REPRODUCE_TOL_MM))
    given.pop("content_sha256", None)
    given.pop("signature", None)  # checked by check_signature
    same(want, given, "", rel_tol(0.0))
    sha = d.get("content_sha256", MISSING)
    if sha is MISSING:
        raise InputError("field 'content_sha256' missing: this file cannot prove its records intact")
    if sha != content_sha256(d):
        raise InputError(
            "the file's content does not match content_sha256 (a record such as fit, loo, selection "
            "or the model's diagnostics was changed after it was written)"
        )
    return out


def verify(cal: Calibration) -> None:
    """``Calibration.verify``: the stored pairs hash to ``data_sha256`` and the model reproduces the
    recorded statistics (every per-point residual, the summaries and the outlier flags, to 1e-9 mm)
    and maps its own pairs finitely."""
    if cal.pairs is None:
        raise InputError("the file carries no training pairs, so it cannot prove it is intact")
    if cal.pairs.sha256() != cal.data_sha256:
        raise InputError(f"the training pairs do not match data_sha256: {CHANGED}")
    for label, key, pairs, stats in (
        ("training", "train", cal.fitted_pairs, cal.train),
        ("check", "check", _corrected_check(cal.check_pairs, cal.tcp_offset), cal.check),
    ):
        if pairs is None and stats is None:
            continue
        if pairs is None or stats is None:
            raise InputError(f"the {label} statistics and the {label} pairs must come together")
        with np.errstate(all="ignore"):
            res = cal.model.residuals(pairs.uv_px, pairs.xyz_mm)
        if not np.isfinite(res).all():
            raise InputError(f"the model maps its own {label} pairs to no finite point: {CHANGED_OR_DAMAGED}")
        try:
            with np.errstate(all="ignore"):
                # the training outliers as calibrate flags them: studentized by the pairs' leverage
                lev = pair_leverage(cal.model, pairs.uv_px, pairs.xyz_mm) if key == "train" else None
                again = stats_from_residuals(res, pairs.ids, leverage=lev).to_dict()
            same(again, stats_dict(stats), key, rel_tol(REPRODUCE_TOL_MM, relative=False))
        except InputError as exc:
            raise InputError(
                f"the model does not reproduce its recorded {label} errors (to {REPRODUCE_TOL_MM:g} mm; "
                f"{exc.reason.removesuffix(': ' + CHANGED)}): {CHANGED_OR_DAMAGED}"
            ) from None


def _malformed(exc: Exception) -> str:
    what = f"field {exc.args[0]!r} missing" if isinstance(exc, KeyError) else f"{type(exc).__name__}: {exc}"
    return f"malformed calibration file ({what})"


def _v1_refusal(cls, d: dict) -> str:
    """Why a schema_version 1 file is refused: a field version 1 never had (a newer file relabelled),
    a malformed version 1 file, or — an intact-looking one — that it cannot prove itself."""
    extra = sorted(k for k in d if k not in V1_FIELDS)
    if extra:
        return (
            f"field 'schema_version' is 1, but the file has field '{extra[0]}', which no schema_version 1 "
            "file has: a newer file relabelled as version 1 (to skip its proof) is refused"
        )
    try:
        check_numbers(d, "")
        _from_dict(cls, d, 1)
    except InputError as exc:
        return str(exc)
    except (KeyError, TypeError, ValueError, AttributeError, IndexError, OverflowError) as exc:
        return _malformed(exc)
    return (
        "field 'schema_version': 1 is a file written by eyetohand 0.1, which carries no pairs and so "
        "cannot prove it is intact (its model reproducing its recorded errors): calibrate its pairs "
        "again with this eyetohand"
    )


CHANGED_OR_DAMAGED = "the file was changed or damaged after it was written"


def _as_written(message: str, d: dict) -> str:
    """A refusal's words. A file whose content still matches its content_sha256 is as it was
    written: where this eyetohand then does not reproduce what it records, the file was written by
    an eyetohand that computed it differently (or edited and re-sealed) — say that, not "changed"."""
    tail = next((t for t in (CHANGED_OR_DAMAGED, CHANGED) if message.endswith(t)), None)
    if tail is None:
        return message
    try:
        sealed = isinstance(d.get("content_sha256"), str) and d["content_sha256"] == content_sha256(d)
    except (TypeError, ValueError, OverflowError):
        sealed = False
    if not sealed:
        return message
    by = d.get("eyetohand_version")
    by = f" ({by})" if isinstance(by, str) else ""
    return (
        f"{message[: -len(tail)]}the file is as written (its content_sha256 checks), so the eyetohand "
        f"that wrote it{by} computed this differently from this one ({__version__}), or the file was "
        "edited and re-sealed; calibrate its pairs again with this version"
    )


FREE_FIELDS = ("created_utc", "eyetohand_version", "notes", "warnings")
"""Top-level fields of the file that are free text: checked for type only, never for value."""
COVARIANCE_TOL = 1e-6
"""A stored covariance entry may differ from the recomputed one by this fraction of
sqrt(C_ii C_jj) (room for another machine's linear algebra; the recomputed one is used)."""


def content_sha256(d: dict) -> str:
    """SHA-256 of a calibration file's content as canonical JSON (sorted keys, no spaces), leaving
    out the free text (``FREE_FIELDS``) and the hash itself: any change of a number, however small,
    or of a record (fit, statistics, selection, diagnostics) changes it."""
    body = {k: v for k, v in d.items() if k not in FREE_FIELDS and k not in ("content_sha256", "signature")}
    canon = json.dumps(body, sort_keys=True, separators=(",", ":"), allow_nan=False)
    return sha256_hex(canon.encode())


def derived_region(model: Model, fitted: PointPairs) -> CalibratedRegion:
    """The calibrated region of a model fitted on ``fitted`` (as
    :func:`eyetohand.calibration.fit.calibrate` makes it)."""
    if model.height_rule is HeightRule.GIVEN:
        return CalibratedRegion.from_pairs(fitted.uv_px, fitted.xyz_mm, plane_z_mm=None)
    if model.height_rule is HeightRule.PLANE:  # the model's own plane (the one height rule)
        plane_z, slope = model.plane_z_mm, model.plane_slope
    else:  # the paper's B computes z; at one height its region's plane is the pairs' plane
        plane = fit_height_plane(fitted.xyz_mm)
        if plane.one_height:
            plane_z, slope = plane.z0_mm, plane.slope
        else:
            plane_z, slope = float(np.mean(fitted.xyz_mm[:, 2])), (0.0, 0.0)
    return CalibratedRegion.from_pairs(fitted.uv_px, fitted.xyz_mm, plane_z_mm=plane_z, plane_slope=slope)


def stats_dict(s: Stats) -> dict:
    try:
        return s.to_dict()
    except (TypeError, AttributeError):  # points of the wrong type: compared (and refused) as given
        return {"n": s.n, "rms_mm": s.rms_mm, "points": list(s.points)}


def _same_uncertainty(
    unc: Uncertainty, given, model: Model, fitted: PointPairs, region: CalibratedRegion
) -> None:
    """The stored uncertainty against the one recomputed from the pairs: same shape and types,
    noise and sigma_mm (at the pairs and the hull) within 1e-9 mm, covariance within
    ``COVARIANCE_TOL`` of its scale."""
    want = unc.to_dict()
    sd = np.sqrt(np.abs(np.diag(unc.covariance)))

    def tol(path: str, w: float) -> float:
        if path.startswith("uncertainty.covariance["):
            i, j = (int(k) for k in path[len("uncertainty.covariance[") : -1].split("]["))
            return COVARIANCE_TOL * float(sd[i] * sd[j])
        return REPRODUCE_TOL_MM

    same(want, given, "uncertainty", tol)
    stored = Uncertainty.from_dict(given, model.n_covariance())
    uv = np.vstack([fitted.uv_px, region.hull_px])
    z_mid = float(np.mean(fitted.xyz_mm[:, 2]))
    z = np.concatenate([fitted.xyz_mm[:, 2], np.full(len(region.hull_px), z_mid)])
    if model.height_rule is HeightRule.COMPUTED:
        z = np.zeros(len(uv))
    with np.errstate(all="ignore"):
        diff = np.abs(stored.sigma_mm(model, uv, z) - unc.sigma_mm(model, uv, z))
    if not (diff <= REPRODUCE_TOL_MM).all():
        raise InputError(
            "field 'uncertainty' does not reproduce sigma_mm from the training pairs "
            f"(to {REPRODUCE_TOL_MM:g} mm): {CHANGED}"
        )


def _stored_uncertainty(d: dict, model: Model) -> Uncertainty | None:
    """The file's uncertainty record, parsed; one of another shape than this eyetohand computes (e.g.
    a lens model's covariance before it held the lens terms) is refused as computed differently."""
    if d.get("uncertainty") is None:
        return None
    try:
        return Uncertainty.from_dict(d["uncertainty"], model.n_covariance())
    except InputError as exc:
        raise InputError(_as_written(f"{str(exc).rstrip('.')}: {CHANGED}", d)) from None


def corrected(pairs: PointPairs | None, tcp: TcpOffset | None) -> PointPairs | None:
    if pairs is None or tcp is None:
        return pairs
    # here: only a file with a tool offset needs solve.tcp_offset (1.0 ms of `apply`'s start, measured)
    from eyetohand.solve import correct_pairs

    return correct_pairs(pairs, tcp.offset_mm)


def _corrected_check(pairs: PointPairs | None, tcp: TcpOffset | None) -> PointPairs | None:
    if pairs is None or tcp is None or pairs.angle_deg is None:
        return pairs
    return corrected(pairs, tcp)


def _stats(d) -> Stats | None:
    if d is None:
        return None
    if not isinstance(d, dict):
        raise InputError("statistics must be an object")
    return Stats.from_dict(d)


def _from_dict(cls, d: dict, ver: int) -> Calibration:
    model = model_from_dict(d["model"])
    f = d["fit"]
    if not isinstance(f, dict):
        raise InputError("'fit' must be an object")
    _typed(f, "fit", FIT_TYPES)
    f = dict(f)
    known = {k: f.pop(k) for k in list(f) if k in FitInfo.__dataclass_fields__}
    known["history"] = tuple(float(v) for v in known.get("history", ()))
    fit = FitInfo(**known, extra=f)
    size = d.get("image_size")
    if size is not None and (
        not isinstance(size, list)
        or len(size) != 2
        or not all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in size)
    ):
        raise InputError("'image_size' must be [width, height] in whole pixels")
    for key in ("notes", "warnings"):
        if not isinstance(d.get(key, []), list) or not all(isinstance(s, str) for s in d.get(key, [])):
            raise InputError(f"'{key}' must be a list of strings")
    sha = d.get("data_sha256", "")
    if not isinstance(sha, str):
        raise InputError("'data_sha256' must be a string")
    for key in ("train", "check", "loo"):
        if d.get(key) is not None or key == "train":
            _typed_stats(d.get(key, MISSING), key)
    if d.get("tcp_offset") is not None:
        _typed(d["tcp_offset"], "tcp_offset", TCP_TYPES)
    sel = d.get("selection")
    if sel is not None:
        _typed(sel, "selection", {"chosen": str, "reason": str, "candidates": list})
        for i, c in enumerate(sel["candidates"]):
            _typed(c, f"selection.candidates[{i}]", {"model": str, "unknowns": int})
    for key in ("created_utc", "eyetohand_version"):
        if not isinstance(d.get(key, ""), str):
            raise InputError(f"field '{key}' must be a string")
    extra: dict[str, object] = {}
    if ver >= 2:
        extra = {
            "region": CalibratedRegion.from_dict(d["region"]) if d.get("region") is not None else None,
            "uncertainty": _stored_uncertainty(d, model),
            "pairs": (
                pairs_from_records(d["pairs"], "pairs", label="pairs") if d.get("pairs") is not None else None
            ),
            "check_pairs": (
                pairs_from_records(d["check_pairs"], "check_pairs", label="check_pairs")
                if d.get("check_pairs") is not None
                else None
            ),
            "warnings": tuple(d.get("warnings", ())),
        }
        if extra["region"] is None:
            raise InputError("field 'region' missing: a calibration must record where it was calibrated")
        if d.get("plate") is not None:
            # only a plate file loads the plate's modules (its spec, the touches): apply of others stays lean
            from eyetohand.calibration.plate_record import PlateRecord

            pairs = extra["pairs"]
            extra["plate"] = PlateRecord.from_dict(
                d["plate"], pairs if isinstance(pairs, PointPairs) else None, model
            )
    return cls(
        model=model,
        fit=fit,
        train=Stats.from_dict(d["train"]),
        check=_stats(d.get("check")),
        loo=_stats(d.get("loo")),
        data_sha256=sha,
        image_size=tuple(size) if size else None,
        notes=tuple(d.get("notes", ())),
        selection=d.get("selection"),
        tcp_offset=TcpOffset.from_dict(d["tcp_offset"]) if d.get("tcp_offset") else None,
        created_utc=str(d.get("created_utc", "")),
        version=str(d.get("eyetohand_version", "")),
        **extra,
    )


_NUM = (int, float)
FIT_TYPES: dict = {
    "optimizer": str,
    "objective": str,
    "fitness": _NUM,
    "history": list,
    "nfev": int,
    "nit": int,
    "seconds": _NUM,
    "seed": (int, type(None)),
    "message": str,
}
TCP_TYPES: dict = {
    "offset_mm": list,
    "std_mm": list,
    "model": str,
    "reference_angle_deg": _NUM,
    "n_turned": int,
    "n_pairs": int,
    "rms_mm": _NUM,
}
STATS_TYPES: dict = {
    "n": int,
    "rms_mm": _NUM,
    "mean_mm": _NUM,
    "max_mm": _NUM,
    "p95_mm": _NUM,
    "outliers": list,
    "points": list,
}
POINT_TYPES: dict = {
    "id": str,
    "dx_mm": _NUM,
    "dy_mm": _NUM,
    "dz_mm": _NUM,
    "error_mm": _NUM,
    "outlier": bool,
}


def _typed(d, path: str, types: dict) -> None:
    """Refuse unless ``d`` is an object with every key of ``types`` of its type (a bool is no number)."""
    if not isinstance(d, dict):
        raise InputError(f"field '{path}' must be an object, got {kind_of(d)}")
    for key, t in types.items():
        if key not in d:
            raise InputError(f"field '{path}.{key}' missing")
        v = d[key]
        ok = isinstance(v, t) and not (isinstance(v, bool) and t is not bool)
        if not ok:
            want = "a number" if t in (_NUM, int) else KIND.get(t, "null or a number")
            raise InputError(f"field '{path}.{key}' must be {want}, got {kind_of(v)}")
    for key in ("history", "offset_mm", "std_mm"):
        if key in types and not all(isinstance(x, _NUM) and not isinstance(x, bool) for x in d[key]):
            raise InputError(f"field '{path}.{key}' must be a list of numbers")
    for key in ("offset_mm", "std_mm"):
        if key in types and len(d[key]) != 2:
            raise InputError(f"field '{path}.{key}' must be two numbers")


def _typed_stats(d, path: str) -> None:
    if d is MISSING:
        raise InputError(f"field '{path}' missing")
    _typed(d, path, STATS_TYPES)
    for i, p in enumerate(d["points"]):
        _typed(p, f"{path}.points[{i}]", POINT_TYPES)
    if not all(isinstance(x, str) for x in d["outliers"]):
        raise InputError(f"field '{path}.outliers' must be a list of strings")
    if d["n"] != len(d["points"]):
        raise InputError(f"field '{path}.n' is {d['n']}, but '{path}.points' has {len(d['points'])} entries")
