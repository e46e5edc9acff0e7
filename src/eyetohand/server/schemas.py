"""Request and response models of the JSON API: they are the OpenAPI schema (types, units, limits)."""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    Field,
    StrictBool,
    ValidationInfo,
    WithJsonSchema,
    field_validator,
)
from pydantic import Strict as StrictType

from eyetohand.calibration import (
    MAX_IMAGE_SIDE_PX,
    check_image_size,
    check_part_diameter,
    check_target_diameter,
    resolve_model,
)
from eyetohand.core import MAX_PAIRS, InputError, pair_count_refusal
from eyetohand.geometry import check_symmetry
from eyetohand.models import MODEL_CHOICES
from eyetohand.server.storage import clean_text, is_id_like
from eyetohand.solve import (
    OBJECTIVES,
    OPTIMIZERS,
    SEED_MAX,
    check_objective,
    check_seed,
    check_solver_options,
    get_solver,
)

MAX_BODY_BYTES = 64 * 1024 * 1024
"""Largest request body (bytes); a larger one gets 413."""
MAX_POINTS = 1_000_000
"""Most image points in one image-to-robot request; more gets 413."""
"""Most point pairs (or check pairs) in one fit request. Measured on a 2-core machine: ``auto``
on 2 000 pairs holds the fit worker ~21 s at ~440 MiB; 5 000 took ~3 min at 1.9 GiB."""
MAX_PAIRS_CAP = 1_000_000
"""Highest ``max_pairs`` a request may ask for (the body limits bound it first)."""
MAX_FIT_BODY_BYTES = 4 * 1024 * 1024
"""Largest body of a fit (and every other non-mapping) request: 2 × 2 000 pairs with 64-character
ids, indented, fit in 2 MiB; larger is refused (413) from Content-Length, before parsing."""
MAX_TEXT_CHARS = 16 * 1024 * 1024
"""Longest CSV/JSON text sent to /api/pairs/parse."""
MAX_PARSE_BODY_BYTES = MAX_TEXT_CHARS + 64 * 1024
"""Largest body of /api/pairs/parse."""
MAX_NAME = 100
MAX_PARTICLES = 1000
MAX_ITERATIONS = 1000
MAX_PSO_WORK = 500_000
"""Default limit of particles × iterations for one PSO fit (the paper's 200 × 150 is 30 000)."""

# strict: a boolean or a string is not a number (an int is a float, as in JSON)
Finite = Annotated[float, StrictType(), Field(allow_inf_nan=False)]
Int = Annotated[int, StrictType()]


def _name(text: str) -> str:
    text = clean_text(text, "name")
    if not text.strip():
        raise ValueError("a name needs a visible character")
    if text != text.strip():
        raise ValueError("a name may not begin or end with white space")
    if is_id_like(text):
        raise ValueError(f"{text!r} is only digits and would read as an id; add a letter")
    return text


def _pair_id(text: str) -> str:
    return clean_text(text, "id")


def _label(text: str) -> str:
    return clean_text(text, "text label")


Name = Annotated[
    str,
    Field(
        min_length=1,
        max_length=MAX_NAME,
        description="display name: 1–100 characters in NFC, no control or format (zero-width, bidi) "
        "characters, not only digits (that reads as an id), no leading/trailing space; "
        "stored as data only",
    ),
    AfterValidator(_name),
]
PairId = Annotated[str, Field(min_length=1, max_length=64), AfterValidator(_pair_id)]
Note = Annotated[str, Field(max_length=200), AfterValidator(_label)]


def _library_rule(check):
    """The library's own rule for a field (the one the CLI and the TCP service apply): a request
    that breaks it hears the library's words, not pydantic's."""

    def validate(value):
        try:
            check(value)
        except InputError as exc:
            raise ValueError(exc.reason) from None
        return value

    return AfterValidator(validate)


def _server_limit(limit: int, what: str):
    """A limit of this service (not of the library): it says so."""

    def validate(value: int) -> int:
        if value > limit:
            raise ValueError(f"{value} {what} is more than this server's limit of {limit}")
        return value

    return AfterValidator(validate)


def _enum(values) -> WithJsonSchema:
    return WithJsonSchema({"type": "string", "enum": list(values)})


# names checked by the library (its words) and listed as an enum in the schema
ModelName = Annotated[str, StrictType(), _library_rule(resolve_model), _enum(MODEL_CHOICES)]
OptimizerName = Annotated[str, StrictType(), _library_rule(get_solver), _enum(OPTIMIZERS)]
ObjectiveName = Annotated[str, StrictType(), _library_rule(check_objective), _enum(OBJECTIVES)]
Symmetry = Annotated[
    int,
    StrictType(),
    _library_rule(check_symmetry),
    WithJsonSchema({"type": "integer", "minimum": 1, "maximum": 360}),
]
ImageSize = Annotated[
    tuple[Int, Int],
    _library_rule(check_image_size),
    WithJsonSchema(
        {
            "type": "array",
            "items": {"type": "integer", "minimum": 1, "maximum": MAX_IMAGE_SIDE_PX},
            "minItems": 2,
            "maxItems": 2,
        }
    ),
]
TargetDiameter = Annotated[
    float,
    StrictType(),
    _library_rule(check_target_diameter),
    WithJsonSchema({"type": "number", "exclusiveMinimum": 0}),
]
PartDiameter = Annotated[
    float,
    StrictType(),
    _library_rule(check_part_diameter),
    WithJsonSchema({"type": "number", "minimum": 0}),
]
Seed = Annotated[
    int,
    StrictType(),
    _library_rule(check_seed),
    WithJsonSchema({"type": "integer", "minimum": 0, "maximum": SEED_MAX}),
]
Particles = Annotated[
    int,
    StrictType(),
    _library_rule(lambda v: check_solver_options({"n_particles": v})),
    _server_limit(MAX_PARTICLES, "particles"),
    WithJsonSchema({"type": "integer", "minimum": 2, "maximum": MAX_PARTICLES}),
]
Iterations = Annotated[
    int,
    StrictType(),
    _library_rule(lambda v: check_solver_options({"iterations": v})),
    _server_limit(MAX_ITERATIONS, "iterations"),
    WithJsonSchema({"type": "integer", "minimum": 1, "maximum": MAX_ITERATIONS}),
]


class Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


class PairsCapped(Strict):
    """A request with pair lists (``pairs``, ``check``): each holds at most ``max_pairs`` pairs, refused
    with the words of the CLI's ``--max-pairs`` (:func:`eyetohand.core.pair_count_refusal`). Declared
    first, so it is validated before the lists that read it."""

    max_pairs: Annotated[int, StrictType()] = Field(
        MAX_PAIRS,
        ge=1,
        le=MAX_PAIRS_CAP,
        description="refuse a list of more pairs than this (far more is usually a mix-up); raise it "
        "for one large collection, as the CLI's --max-pairs",
    )

    @field_validator("pairs", "check", check_fields=False)
    @classmethod
    def _capped(cls, v, info: ValidationInfo):
        cap = info.data.get("max_pairs")
        if v is not None and cap is not None and len(v) > cap:
            raise ValueError(pair_count_refusal(len(v), cap))
        return v


class PairIn(Strict):
    """One point pair: the image centre (u, v) in px and the robot position (x, y, z) in mm."""

    id: PairId | None = Field(None, description="pair id (default: its index)")
    u: Finite = Field(description="image column, px")
    v: Finite = Field(description="image row, px")
    x: Finite = Field(description="robot x, mm")
    y: Finite = Field(description="robot y, mm")
    z: Finite | None = Field(None, description="robot z, mm (all pairs or none; none means z = 0)")


class FitOptions(PairsCapped):
    pairs: list[PairIn] = Field(min_length=1, description="calibration pairs")
    check: list[PairIn] | None = Field(None, min_length=1, description="check pairs, not used for fitting")
    model: ModelName = Field("auto", description="transform model; 'auto' picks by cross-validation")
    optimizer: OptimizerName = Field("lm", description="solver refining the model")
    objective: ObjectiveName = Field("l2", description="robot-space objective (mm)")
    seed: Seed | None = Field(None, description="seed of the stochastic solvers")
    exclude: list[Annotated[str, Field(max_length=64), AfterValidator(_pair_id)]] = Field(
        default_factory=list,
        max_length=MAX_PAIRS_CAP,
        description="ids of pairs left out of the fit (their errors are still reported)",
    )
    particles: Particles = Field(200, description="swarm size (pso, hybrid-pso)")
    iterations: Iterations = Field(150, description="iterations (pso, hybrid-pso)")
    image_size: ImageSize | None = Field(
        None, description="image width and height, px (sets the distortion centre)"
    )
    target_diameter_mm: TargetDiameter | None = Field(
        None,
        description="the circle target's diameter, mm: correct the detected centres for its "
        "perspective bias (fit, correct with the fit's maps, refit)",
    )


class CreateCalibration(FitOptions):
    name: Name


class NewVersion(FitOptions):
    note: Note = Field("refit", description="what changed")


class SaveJob(Strict):
    name: Name | None = Field(None, description="save as a new calibration with this name")
    calibration_id: Int | None = Field(
        None, ge=1, le=2**62, description="or: add the result as a new version of this calibration"
    )
    note: Note = ""


class Rename(Strict):
    name: Name


class ImportCalibration(Strict):
    """A calibration file (as ``eyetohand calibrate -o`` writes it) to store: a new calibration with
    this name, or a new version of the calibration that has it. The file must prove itself intact."""

    name: Name
    calibration: dict[str, Any] = Field(description="the calibration file's JSON object")
    note: Note = "imported"


class VerifyRequest(PairsCapped):
    pairs: list[PairIn] = Field(min_length=3, description="freshly measured pairs")
    tolerance_mm: Finite = Field(gt=0, description="largest error (mm) a point may have to pass")


class Rollback(Strict):
    version: Int = Field(ge=1, le=2**62, description="the version to make current again")


class MapRequest(Strict):
    points: list[tuple[Finite, Finite]] = Field(
        min_length=1,
        json_schema_extra={"maxItems": MAX_POINTS},
        description=f"image points [u, v] in px; at most {MAX_POINTS} (more gets 413)",
    )
    z: Finite | list[Finite] | None = Field(
        None, description="object height, mm: one value, one per point, or none (calibration plane)"
    )
    angles: list[Finite] | None = Field(
        None, description="image angles, deg from +u towards +v, one per point: answered as rz (deg)"
    )
    symmetry: Symmetry = Field(1, description="fold rz into (-180/s, 180/s] (2: 180° symmetric)")
    tool_rz_offset_deg: Finite | None = Field(
        None, description="the gripper's rz when aligned with the image's +u: rz becomes its command"
    )
    allow_outside: StrictBool = Field(
        False, description="map points outside the calibrated region too (flagged inside=false)"
    )
    sigma: StrictBool = Field(True, description="compute each point's predicted error sigma_mm")
    part_diameter_mm: PartDiameter | list[PartDiameter] | None = Field(
        None,
        description="the circular part's diameter (mm, whatever units says; one, or one per point): its "
        "detected centres are "
        "corrected for perspective as the calibration's circle centres were (0: the points are the "
        "points' own images); a circle-centre calibration refuses detections without it where the bias "
        "exceeds their predicted error",
    )
    # checked by the route with every interface's words (eyetohand.core.output_units): any JSON value
    units: Any = Field(
        None,
        json_schema_extra={"enum": ["mm", "m"]},
        description="length unit of the answer's points and sigma, and of z given here (default mm; "
        "m = mm / 1000)",
    )
    angle_units: Any = Field(
        None, json_schema_extra={"enum": ["deg", "rad"]}, description="unit of the answer's rz (default deg)"
    )


class MapResponse(BaseModel):
    id: int | None = Field(None, description="calibration id (absent for an unsaved job result)")
    version: int | None = None
    units: Literal["mm", "m"] = Field("mm", description="length unit of points and sigma_<units>")
    angle_units: Literal["deg", "rad"] = Field("deg", description="unit of rz_<angle_units>")
    points: list[tuple[float, float, float]] = Field(description="robot points [x, y, z] in units")
    rz_deg: list[float] | None = Field(None, description="robot angles (deg), when angles were given")
    rz_rad: list[float] | None = Field(None, description="the same in rad (angle_units rad)")
    sigma_mm: list[float] | None = Field(None, description="predicted error of each point (mm)")
    sigma_m: list[float] | None = Field(None, description="the same in m (units m)")
    inside: list[bool] = Field(description="whether each point lies in the calibrated region")


class ParseRequest(PairsCapped):
    text: str = Field(
        min_length=1,
        max_length=MAX_TEXT_CHARS,
        description='CSV with header u,v,x,y[,z][,id], or JSON {"pairs": [...]}',
    )
    source: Annotated[str, AfterValidator(_label)] = Field(
        "pasted", max_length=200, description="label used in error messages (e.g. the file's name); data only"
    )


class PairOut(BaseModel):
    id: str
    u: float
    v: float
    x: float
    y: float
    z: float


class ParseResponse(BaseModel):
    source: str
    n: int
    pairs: list[PairOut]
    notes: list[str]
    z_levels_mm: list[float]


class PointErrorOut(BaseModel):
    id: str
    dx_mm: float
    dy_mm: float
    dz_mm: float
    error_mm: float
    outlier: bool


class StatsOut(BaseModel):
    n: int
    rms_mm: float
    mean_mm: float
    max_mm: float
    p95_mm: float
    outliers: list[str]
    points: list[PointErrorOut]


class EvaluateOut(StatsOut):
    warnings: list[str] = Field(
        description="what was found about the pairs, in the CLI's words: pairs evaluated outside the "
        "calibrated region (allow_outside), a mixed-up convention (u and v swapped, …)"
    )


class VectorOut(BaseModel):
    id: str
    u: float
    v: float
    du_px: float | None = Field(description="image displacement equivalent to the error, px")
    dv_px: float | None


class ExpectedAccuracy(BaseModel):
    """The error budget (``calibration.error_budget``): what the check error should be, and why."""

    line: str = Field(description="as eyetohand calibrate prints it")
    where: str = Field(description="check points, or training pixels without them")
    expected_rms_mm: float | None
    measured_rms_mm: float | None
    fit_rms_mm: float | None = Field(description="the fit's own error there")
    touches_rms_mm: float | None = Field(description="a plate's placement by its touches (0 without)")
    measurement_rms_mm: float | None
    noise_mm: float | None = Field(description="the residual noise per axis")
    noise_px_equivalent: float | None
    scale_mm_per_px: float | None


class Summary(BaseModel):
    """A fitted calibration: how it was made and how good it is (all errors in mm)."""

    model: str
    optimizer: str
    objective: str
    fitness_mm: float | None
    history: list[float | None] = Field(description="best fitness after each iteration, mm")
    nfev: int
    seconds: float
    seed: int | None
    uses_z: bool
    plane_z_mm: float | None
    circle_diameter_mm: float | None = Field(
        None,
        description="the calibration maps the centres of circles of this diameter (fitted with "
        "target_diameter_mm: its file's image_points): a detection is mapped with its part's "
        "part_diameter_mm; None: image points as detected",
    )
    n_pairs: int
    excluded_ids: list[str]
    notes: list[str]
    selection: dict[str, Any] | None
    expected_accuracy: ExpectedAccuracy | None = Field(None, description="None without an uncertainty record")
    train: StatsOut
    loo: StatsOut | None
    check: StatsOut | None
    excluded: StatsOut | None
    vectors: dict[str, list[VectorOut]]


class SignatureOut(BaseModel):
    signed_by: str = Field(description="the signer's token name (an import: who imported the signed file)")
    signed_utc: str
    origin: str = Field(description="sign (a signer's act), import (carried by the file), rollback (copied)")
    key_id: str


class CalibrationOut(BaseModel):
    id: int
    name: str
    version: int = Field(description="the version shown")
    current_version: int
    etag: str = Field(
        description="the ETag of the calibration's current state: send it as If-Match to change it"
    )
    created_utc: str
    updated_utc: str
    note: str
    request: dict[str, Any]
    summary: Summary
    signature: SignatureOut | None = Field(None, description="the version's signature (None: unsigned)")
    waits_for_signature: bool = Field(
        False, description="serve --require-signed and this version is unsigned: it is not mapped with"
    )


class CalibrationDetail(CalibrationOut):
    pairs: list[PairOut]
    check: list[PairOut] | None
    calibration: dict[str, Any] = Field(description="the calibration file (what `eyetohand apply` reads)")


class CalibrationBrief(BaseModel):
    id: int
    name: str
    current_version: int
    etag: str = Field(
        description="the ETag of the calibration's current state: send it as If-Match to change it"
    )
    updated_utc: str
    model: str
    optimizer: str
    fitness_mm: float | None
    train_rms_mm: float
    check_rms_mm: float | None
    circle_diameter_mm: float | None = Field(
        None, description="the current version maps the centres of circles of this diameter (see Summary)"
    )


class VersionBrief(BaseModel):
    version: int
    created_utc: str
    note: str
    model: str
    optimizer: str
    fitness_mm: float | None
    train_rms_mm: float
    check_rms_mm: float | None
    signature: SignatureOut | None = None
    waiting: str | None = Field(
        None,
        description="serve --require-signed and this version is not signed with the server's key: why it "
        "is not mapped with, in the words every interface refuses with (None: it may be mapped with)",
    )


class VersionList(BaseModel):
    id: int
    name: str
    current_version: int
    etag: str = Field(
        description="the ETag of the calibration's current state: send it as If-Match to change it"
    )
    versions: list[VersionBrief]


class EvaluateRequest(PairsCapped):
    pairs: list[PairIn] = Field(min_length=1)
    allow_outside: bool = Field(
        False,
        description="evaluate pairs outside the calibrated region or heights too (a warning counts them)",
    )


class CompareRequest(PairsCapped):
    pairs: list[PairIn] = Field(min_length=1)
    check: list[PairIn] = Field(min_length=1)
    seed: Seed = 0


class JobCreated(BaseModel):
    id: str
    kind: Literal["fit", "compare"]
    status: str


class JobProgress(BaseModel):
    unit: str = Field(description="what is counted: images (detection), iterations (PSO), fits (compare)")
    done: int
    total: int
    eta_s: float | None = Field(
        description="seconds left in this step at its rate so far (None: not known yet)"
    )


class JobOut(BaseModel):
    id: str
    kind: Literal["fit", "compare"]
    status: Literal["queued", "running", "done", "failed", "cancelled"]
    phase: str
    iterations: int = Field(description="iterations expected (PSO), else 0")
    history_from: int = Field(description="index of the first entry of history in this answer")
    history: list[float | None] = Field(description="best fitness after each iteration so far, mm")
    elapsed_s: float
    progress: JobProgress | None = Field(
        None, description="the current step counted (images, iterations, fits) with the time it has left"
    )
    result: Summary | None = None
    compare: list[dict[str, Any]] | None = None
    error: dict[str, Any] | None = None
    saved: dict[str, Any] | None = None


class ErrorOut(BaseModel):
    error: str = Field(description="what is wrong, in one line")
    field: str | None = Field(None, description="the request field it is about, e.g. pairs[3].u")
    line: int | None = Field(None, description="line of the pasted/uploaded text, when it is about one")


class SigningMeta(BaseModel):
    key_id: str | None = Field(description="the id of the server's --sign-key (None: it cannot sign)")
    required: bool = Field(description="serve --require-signed: only signed versions are mapped with")


class Meta(BaseModel):
    version: str
    models: list[str]
    optimizers: list[str]
    objectives: list[str]
    presets: dict[str, dict[str, Any]]
    limits: dict[str, int]
    auth: bool
    signing: SigningMeta


# ---------------------------------------------------------------- calibration from uploaded images

MAX_IMAGES = 500
"""Most images in one POST /api/images/calibrate."""
MAX_IMAGES_BODY_BYTES = MAX_BODY_BYTES
"""Largest body of POST /api/images/calibrate (images as base64: ~48 MiB of image files); refused
(413) from Content-Length before parsing."""


def _file_name(text: str) -> str:
    text = clean_text(text, "file name")
    if "/" in text or "\\" in text or text in (".", "..") or not text.strip():
        raise ValueError("a file name without folders, e.g. 'pose_01.png'")
    return text


FileName = Annotated[str, Field(min_length=1, max_length=255), AfterValidator(_file_name)]
Base64 = Annotated[str, Field(max_length=MAX_IMAGES_BODY_BYTES, description="the file's bytes, base64")]


class UploadedFile(Strict):
    name: FileName = Field(description="the file's name (no folders), as the poses CSV names it")
    data_base64: Base64


class ImagesCalibrate(PairsCapped):
    """`eyetohand calibrate-images` from the page: the poses CSV (``image,x,y[,z][,angle]``) and the
    image files it names, detected one by one in the job queue, then fitted."""

    poses: UploadedFile = Field(description="the poses CSV file, bytes as uploaded (UTF-8 expected)")
    images: list[UploadedFile] = Field(min_length=1, max_length=MAX_IMAGES, description="the image files")
    check: list[PairIn] | None = Field(None, min_length=1, description="check pairs, not used for fitting")
    polarity: Literal["auto", "dark", "bright"] = "auto"
    diameter_px: Finite | None = Field(None, description="expected target diameter, px")
    model: ModelName = Field("auto", description="transform model; 'auto' picks by cross-validation")
    optimizer: OptimizerName = Field("lm", description="solver refining the model")
    objective: ObjectiveName = Field("l2", description="robot-space objective (mm)")
    seed: Seed | None = Field(None, description="seed of the stochastic solvers")
    particles: Particles = Field(200, description="swarm size (pso, hybrid-pso)")
    iterations: Iterations = Field(150, description="iterations (pso, hybrid-pso)")
    image_size: ImageSize | None = Field(
        None, description="image width and height, px (sets the distortion centre)"
    )
    target_diameter_mm: TargetDiameter | None = Field(
        None, description="the circle target's diameter, mm: correct the centres for its perspective bias"
    )


class ImageDetectionOut(BaseModel):
    image: str = Field(description="the image as the poses CSV names it")
    ok: bool
    u: float | None = Field(None, description="target centre, image column, px")
    v: float | None = Field(None, description="target centre, image row, px")
    diameter_px: float | None = None
    score: float | None = Field(None, description="detection quality, 0..1")
    reason: str = Field("", description="why the image was left out")


class ImagesJobOut(JobOut):
    poses: int = Field(description="poses in the CSV (0 until it is read)")
    detections: list[ImageDetectionOut] = Field(description="one per pose detected so far, in CSV order")
    left_out: list[str] = Field(description="images whose target was not found (not fitted)")
    unused_images: list[str] = Field(description="uploaded files the poses CSV does not name")
    pairs: list[PairOut] | None = Field(None, description="the detected pairs (id = image), once fitted")
