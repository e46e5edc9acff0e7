"""What the app does with a request, without HTTP: build pairs, fit, summarise, map, run jobs."""

from __future__ import annotations

import dataclasses
import enum
import json
import threading
import time
import uuid
from collections import OrderedDict
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from eyetohand.calibration import (
    AutoModel,
    Calibration,
    FitRequest,
    as_fitted,
    calibrate_request,
    resolve_model,
)
from eyetohand.core import InputError, PointPairs, pairs_from_records
from eyetohand.server.schemas import FitOptions
from eyetohand.solve import Stats, get_solver, stats_from_residuals


class ApiError(Exception):
    """An error answered as ``{"error": message, "field": field}`` with ``status``."""

    def __init__(self, status: int, message: str, field: str | None = None, line: int | None = None):
        super().__init__(message)
        self.status = status
        self.message = message
        self.field = field
        self.line = line

    def to_dict(self) -> dict:
        """The JSON body's fields (``status`` too, for a job's ``error``)."""
        return {"status": self.status, "error": self.message, "field": self.field, "line": self.line}


def input_error(exc: InputError, default_field: str | None = None, status: int = 422) -> ApiError:
    """An InputError from the library as an ApiError: its one-line message, the request field it
    names (``pairs[3].u``, from the error's ``index``/``field``), else ``default_field``, and the
    line of a text it names."""
    return ApiError(status, str(exc), exc.field_path or default_field, exc.line)


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


def split_excluded(pairs: PointPairs, exclude) -> tuple[PointPairs, PointPairs | None]:
    ids = list(pairs.ids)
    for i, pid in enumerate(exclude):
        if pid not in ids:
            raise ApiError(422, f"exclude[{i}]: no pair with id {pid!r}", f"exclude[{i}]")
    mask = np.array([pid in set(exclude) for pid in ids], bool)
    if mask.all():
        raise ApiError(422, "exclude: every pair is excluded; nothing is left to fit", "exclude")
    kept = pairs.subset(~mask)
    return kept, (pairs.subset(mask) if mask.any() else None)


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


def _finite(x) -> float | None:
    x = float(x)
    return x if np.isfinite(x) else None


def _vectors(cal: Calibration, pairs: PointPairs | None) -> list[dict]:
    """Per pair: the image displacement that its robot-space error corresponds to (px)."""
    if pairs is None:
        return []
    try:
        with np.errstate(all="ignore"):
            back = cal.robot_to_image(pairs.xyz_mm)
            d = pairs.uv_px - back
    except Exception:  # a model without a usable inverse: no arrows, the table still shows errors
        d = np.full((len(pairs), 2), np.nan)
    return [
        {"id": pid, "u": float(uv[0]), "v": float(uv[1]), "du_px": _finite(dd[0]), "dv_px": _finite(dd[1])}
        for pid, uv, dd in zip(pairs.ids, pairs.uv_px, d, strict=True)
    ]


def _stats(s: Stats | None) -> dict | None:
    return None if s is None else s.to_dict()


def expected_accuracy(cal: Calibration) -> dict | None:
    """The error budget as ``calibrate`` prints it (``line``) and its figures; None without an
    uncertainty record."""
    from eyetohand.calibration import error_budget

    b = error_budget(cal)
    if b is None:
        return None
    return {
        **{k: v if isinstance(v, str) or v is None else _finite(v) for k, v in b.to_dict().items()},
        "line": b.describe(),
    }


def summarize(cal: Calibration, pairs: PointPairs, check: PointPairs | None, excluded=()) -> dict:
    """The fit's summary; ``pairs`` and ``check`` as given (detected), their per-pair errors taken in
    the form the calibration was fitted on (centres corrected when it records a target diameter)."""
    pairs, check = as_fitted(cal, pairs), as_fitted(cal, check)
    kept, out = split_excluded(pairs, list(excluded)) if excluded else (pairs, None)
    ex_stats = None
    if out is not None:
        ex_stats = stats_from_residuals(cal.model.residuals(out.uv_px, out.xyz_mm), out.ids)
    fit = cal.fit
    return {
        "model": cal.model_name,
        "optimizer": fit.optimizer,
        "objective": fit.objective,
        "fitness_mm": _finite(fit.fitness),
        "history": [_finite(h) for h in fit.history],
        "nfev": int(fit.nfev),
        "seconds": float(fit.seconds),
        "seed": fit.seed,
        "uses_z": bool(cal.model.uses_z),
        "plane_z_mm": cal.model.plane_z_mm,
        "n_pairs": len(kept),
        "excluded_ids": list(excluded),
        "notes": list(cal.notes),
        "selection": cal.selection,
        "expected_accuracy": expected_accuracy(cal),
        "train": cal.train.to_dict(),
        "loo": _stats(cal.loo),
        "check": _stats(cal.check),
        "excluded": _stats(ex_stats),
        "vectors": {
            "train": _vectors(cal, kept),
            "check": _vectors(cal, check),
            "excluded": _vectors(cal, out),
        },
    }


def map_points(
    cal: Calibration,
    points: np.ndarray,
    z,
    *,
    angles=None,
    symmetry: int = 1,
    tool_rz_offset_deg=None,
    allow_outside: bool = False,
    sigma: bool = True,
    part_diameter_mm: float | list[float] | None = None,
):
    """(N, 2) px → the calibration's guarded :class:`~eyetohand.calibration.file.Mapped`, with the
    request's ``z`` (None, a number, or one per point), ``angles`` (one per point) and the part's
    diameter (``Calibration.map``'s ``part_diameter_mm``)."""
    if isinstance(z, list):
        if len(z) != len(points):
            raise ApiError(
                422, f"z: {len(z)} heights for {len(points)} points; give one, or one per point", "z"
            )
        z = np.asarray(z, float)
    if isinstance(part_diameter_mm, list) and len(part_diameter_mm) != len(points):
        raise ApiError(
            422,
            f"part_diameter_mm: {len(part_diameter_mm)} diameters for {len(points)} points; "
            "give one, or one per point",
            "part_diameter_mm",
        )
    if angles is not None and len(angles) != len(points):
        raise ApiError(
            422, f"angles: {len(angles)} angles for {len(points)} points; give one per point", "angles"
        )
    try:
        with np.errstate(all="ignore"):
            return cal.map(
                points,
                z,
                angle_deg=angles,
                symmetry=symmetry,
                tool_rz_offset_deg=tool_rz_offset_deg,
                allow_outside=allow_outside,
                with_sigma=sigma,
                part_diameter_mm=part_diameter_mm,
            )
    except InputError as exc:
        raise ApiError(422, str(exc), exc.field_path or "z") from None


# ---------------------------------------------------------------------- background jobs


def fit_progress(job: Job, model: str, optimizer: str, iterations: int):
    """Set a fit job's phase; the swarm's progress callback (records the best fitness per
    iteration, stops on cancel), or None for the solvers that do not iterate visibly."""
    job.phase = (
        "choosing the model by cross-validation, then fitting"
        if isinstance(resolve_model(model), AutoModel)
        else f"fitting {model} with {optimizer}"
    )
    if not get_solver(optimizer).is_swarm:  # only a swarm reports progress per iteration
        return None

    def progress(_iteration, best, *_):
        job.history.append(_finite(best))
        done = len(job.history)
        job.step("iterations", min(done, iterations), iterations)
        job.phase = (
            "leave-one-out refits and check points"
            if done >= iterations
            else f"{optimizer}: iteration {done} of {iterations}"
        )
        return job.cancel.is_set()

    return progress


def finish_fit(job: Job, fitted: Fitted, optimizer: str) -> None:
    """The fit's result on its job; a solver without progress (not a swarm, see
    :func:`fit_progress`) gives its whole history at once."""
    job.fitted = fitted
    if not get_solver(optimizer).is_swarm:
        job.history = [_finite(h) for h in fitted.calibration.fit.history]


class JobKind(enum.StrEnum):
    """What a job does (its JSON ``kind``: the value)."""

    FIT = "fit"
    COMPARE = "compare"


@dataclass
class Job:
    id: str
    kind: JobKind
    iterations: int
    status: str = "queued"
    phase: str = "waiting for a free worker"
    history: list[float | None] = field(default_factory=list)
    created: float = field(default_factory=time.monotonic)
    started: float | None = None
    finished: float | None = None
    fitted: Fitted | None = None
    compare: list[dict] | None = None
    error: ApiError | None = None  # why it failed (the API's error, a 500 for anything unexpected)
    saved: dict | None = None
    cancel: threading.Event = field(default_factory=threading.Event)
    done: threading.Event = field(default_factory=threading.Event)
    # the current step of work counted in units (images detected, iterations, fits of a comparison):
    # what it is, how many are done of how many, and when its first unit started
    unit: str = ""
    units_done: int = 0
    units_total: int = 0
    unit_started: float = 0.0

    def step(self, unit: str, done: int, total: int) -> None:
        """Count the current step's progress (a new ``unit`` starts the clock of its estimate)."""
        if unit != self.unit:
            self.unit, self.unit_started = unit, time.monotonic()
        self.units_done, self.units_total = done, total

    def progress(self) -> dict | None:
        """``{unit, done, total, eta_s}``: ``eta_s`` the time left in this step at its rate so far
        (None before its first unit is done)."""
        if not self.units_total:
            return None
        eta = None
        if 0 < self.units_done and self.status == "running":
            rate = (time.monotonic() - self.unit_started) / self.units_done
            eta = round(rate * max(self.units_total - self.units_done, 0), 1)
        return {"unit": self.unit, "done": self.units_done, "total": self.units_total, "eta_s": eta}

    def elapsed(self) -> float:
        if self.started is None:
            return 0.0
        return (self.finished or time.monotonic()) - self.started

    def view(self, since: int = 0) -> dict:
        since = max(0, min(since, len(self.history)))
        return {
            "id": self.id,
            "kind": self.kind,
            "status": self.status,
            "phase": self.phase,
            "iterations": self.iterations,
            "history_from": since,
            "history": self.history[since:],
            "elapsed_s": round(self.elapsed(), 3),
            "progress": self.progress(),
            "result": self.fitted.summary() if (self.fitted and self.status == "done") else None,
            "compare": self.compare,
            "error": None if self.error is None else self.error.to_dict(),
            "saved": self.saved,
        }


class Jobs:
    """Fits and comparisons run one at a time on a worker thread (the machine's cores go to the
    solver's vectorised numpy); at most ``max_pending`` wait. Finished jobs are kept (the latest
    ``keep``) so that their results can be saved, mapped through or looked at again."""

    def __init__(self, max_pending: int = 8, keep: int = 50, workers: int = 1, max_pso_work: int = 500_000):
        self.max_pso_work = max_pso_work
        self._workers = workers
        self._pool: ThreadPoolExecutor | None = None
        self._jobs: OrderedDict[str, Job] = OrderedDict()
        self._lock = threading.Lock()
        self.max_pending = max_pending
        self.keep = keep

    def get(self, job_id: str) -> Job:
        with self._lock:
            job = self._jobs.get(job_id)
        if job is None:
            raise ApiError(
                404, f"no job {job_id!r} (finished jobs are kept until {self.keep} newer ones)", "id"
            )
        return job

    def submit(self, kind: JobKind, work, iterations: int = 0) -> Job:
        with self._lock:
            pending = sum(1 for j in self._jobs.values() if j.status in ("queued", "running"))
            if pending >= self.max_pending:
                raise ApiError(429, f"{pending} jobs are queued or running; wait for one to finish")
            job = Job(uuid.uuid4().hex, kind, iterations)
            self._jobs[job.id] = job
            finished = [k for k, j in self._jobs.items() if j.done.is_set()]
            for k in finished[: max(0, len(finished) - self.keep)]:
                del self._jobs[k]
        with self._lock:
            if self._pool is None:
                self._pool = ThreadPoolExecutor(max_workers=self._workers, thread_name_prefix="eyetohand-job")
            self._pool.submit(self._run, job, work)
        return job

    def _run(self, job: Job, work) -> None:
        if job.cancel.is_set():
            job.status, job.phase = "cancelled", "cancelled before it started"
            job.done.set()
            return
        job.status, job.started = "running", time.monotonic()
        try:
            work(job)
            if job.cancel.is_set():
                job.status, job.phase, job.fitted = "cancelled", "cancelled", None
            else:
                job.status, job.phase = "done", "done"
        except ApiError as exc:
            job.status, job.phase, job.error = "failed", "failed", exc
        except Exception as exc:  # noqa: BLE001 - a job must report, not vanish
            job.status, job.phase = "failed", "failed"
            job.error = ApiError(500, f"internal error: {type(exc).__name__}: {exc}")
        finally:
            job.finished = time.monotonic()
            job.done.set()

    def check_pso_work(self, optimizer: str, particles: int, iterations: int) -> bool:
        """Whether ``optimizer`` is a swarm; refuses (422) a swarm of more particles × iterations
        than this server's limit."""
        pso = get_solver(optimizer).is_swarm
        if pso and particles * iterations > self.max_pso_work:
            raise ApiError(
                422,
                f"particles × iterations = {particles} × {iterations} = "
                f"{particles * iterations}, more than this server's limit of {self.max_pso_work}",
                "iterations",
            )
        return pso

    def fit_job(self, opts: FitOptions) -> Job:
        pso = self.check_pso_work(opts.optimizer, opts.particles, opts.iterations)

        def work(job: Job) -> None:
            fitted = fit(opts, fit_progress(job, opts.model, opts.optimizer, opts.iterations))
            finish_fit(job, fitted, opts.optimizer)

        return self.submit(JobKind.FIT, work, opts.iterations if pso else 0)

    def compare_job(self, pairs: PointPairs, check: PointPairs, seed: int) -> Job:
        from eyetohand.calibration import compare

        def work(job: Job) -> None:
            job.phase = "fitting every model with every solver, then scoring on the check points"

            def progress(done: int, total: int, row: dict) -> bool:
                job.step("fits", done, total)
                job.phase = f"fit {done} of {total} done ({row['model']} + {row['optimizer']})"
                return job.cancel.is_set()

            try:
                rows = compare(pairs, check, seed=seed, progress=progress)
            except InputError as exc:
                raise input_error(exc, "pairs") from None
            job.compare = [
                {k: (_finite(v) if isinstance(v, float) else v) for k, v in r.items()} for r in rows
            ]
            for r in job.compare:
                if "check_errors_mm" in r:
                    r["check_errors_mm"] = [_finite(e) for e in r["check_errors_mm"]]

        return self.submit(JobKind.COMPARE, work)

    def shutdown(self) -> None:
        """Cancel queued and running jobs and wait for the worker (a later submit starts a new one)."""
        with self._lock:
            for j in self._jobs.values():
                j.cancel.set()
            pool, self._pool = self._pool, None
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)
        with self._lock:
            for j in self._jobs.values():
                if not j.done.is_set():  # never started: its future was cancelled
                    j.status, j.phase = "cancelled", "cancelled: the server stopped"
                    j.done.set()
