"""A fit request without HTTP: the pairs from records or text, the excluded rows, the fit and its summary."""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass

from eyetohand.calibration import (
    Calibration,
    FitRequest,
    calibrate_request,
)
from eyetohand.core import InputError, PointPairs, pairs_from_records
from eyetohand.server.errors import ApiError, input_error
from eyetohand.server.schemas import FitOptions
from eyetohand.server.summaries import split_excluded, summarize


def to_pairs(records, label: str) -> PointPairs:
    """Validated PointPairs from request records; errors name ``label[i].field``."""
    recs = [{k: v for k, v in r.model_dump().items() if v is not None} for r in records]
    try:
        pairs = pairs_from_records(recs, source=None, label=label)  # messages name label[i] only
    except InputError as exc:
        raise input_error(exc, label) from None
    notes = tuple(n.replace("None: ", f"{label}: ", 1) if n.startswith("None: ") else n for n in pairs.notes)
    return dataclasses.replace(pairs, source=label, notes=notes)


def parse_text(text: str, source: str, max_pairs: int | None = None) -> PointPairs:
    """Pairs from CSV or JSON text, with the same rules and messages as ``eyetohand calibrate``
    (its ``--max-pairs`` cap as ``max_pairs``)."""
    from eyetohand.core import pairs_from_text

    name = source.strip() or "pasted"
    try:
        return pairs_from_text(text, name, max_pairs=max_pairs)
    except InputError as exc:
        # the request field is the text; an entry of a JSON text is named inside it
        fld = "text" if exc.index is None else f"text: {exc.field_path}"
        raise ApiError(422, str(exc), fld, exc.line) from None


@dataclass
class Fitted:
    """A fit's result: the calibration with the inputs it was made from."""

    calibration: Calibration
    pairs: PointPairs  # every pair given, excluded ones included
    check: PointPairs | None
    excluded: tuple[str, ...]
    request: dict

    def summary(self) -> dict:
        return summarize(self.calibration, self.pairs, self.check, self.excluded)


def fit(opts: FitOptions, callback=None) -> Fitted:
    pairs = to_pairs(opts.pairs, "pairs")
    check = to_pairs(opts.check, "check") if opts.check else None
    kept, _ = split_excluded(pairs, opts.exclude)
    try:
        asked = FitRequest.from_names(
            opts.model,
            opts.optimizer,
            opts.objective,
            seed=opts.seed,
            n_particles=opts.particles,
            iterations=opts.iterations,
            image_size=opts.image_size,
            target_diameter_mm=opts.target_diameter_mm,
        )
        cal = calibrate_request(asked, kept, check=check, callback=callback)
    except InputError as exc:
        raise input_error(exc, "pairs") from None
    try:  # what is stored and answered must be finite: a fit that is not is the pairs' fault
        json.dumps(cal.to_dict(), allow_nan=False)
    except ValueError:
        raise ApiError(
            422,
            f"pairs: model {cal.model_name!r} gives non-finite values on these pairs "
            "(degenerate geometry?); try another model",
            "pairs",
        ) from None
    request = opts.model_dump(exclude={"pairs", "check", "name", "note", "max_pairs"})
    return Fitted(cal, pairs, check, tuple(opts.exclude), request)
