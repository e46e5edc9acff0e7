"""The app's background jobs (a fit, a comparison): their state, progress and queue, without HTTP."""

from __future__ import annotations

import enum
import threading
import time
import uuid
from collections import OrderedDict
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

from eyetohand.calibration import (
    AutoModel,
    resolve_model,
)
from eyetohand.core import InputError, PointPairs
from eyetohand.server.errors import ApiError, input_error
from eyetohand.server.fitting import Fitted, fit
from eyetohand.server.schemas import FitOptions
from eyetohand.server.summaries import finite_or_none
from eyetohand.solve import get_solver


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
        job.history.append(finite_or_none(best))
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
        job.history = [finite_or_none(h) for h in fitted.calibration.fit.history]


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
                {k: (finite_or_none(v) if isinstance(v, float) else v) for k, v in r.items()} for r in rows
            ]
            for r in job.compare:
                if "check_errors_mm" in r:
                    r["check_errors_mm"] = [finite_or_none(e) for e in r["check_errors_mm"]]

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
