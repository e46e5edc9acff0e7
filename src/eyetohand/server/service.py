"""The one service object behind the routes (``app.state.service``): the store, the cache of decoded
calibrations, the job queue and the server's limits.

Threads: routes that touch the store run on the thread pool; the mapping routes run on the event
loop and read only :meth:`Service.cached` (a dict look-up under a lock, never the database). The
cache is filled from the pool, and every write that changes which version is current (new version,
rollback, delete) drops that calibration's entries, with a generation counter so that a read that
raced the write cannot put the old version back."""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING

from eyetohand.calibration import Calibration
from eyetohand.core import PointPairs, TokenTable, pairs_from_records
from eyetohand.server.errors import ApiError
from eyetohand.server.fitting import Fitted, fit
from eyetohand.server.jobs import Job, JobKind, Jobs, finish_fit, fit_progress
from eyetohand.server.schemas import FitOptions, ImagesCalibrate
from eyetohand.server.signatures import SigningPolicy
from eyetohand.server.storage import Record, Store, Version, require_match
from eyetohand.server.summaries import summarize

if TYPE_CHECKING:
    from eyetohand.server.follow import Follower

# reads of one calibration before it is returned uncached: a change noticed during each of them (a
# store written to that fast) is rare, and the caller still gets what the last read said
_READS = 3


@dataclass(frozen=True)
class Limits:
    max_body_bytes: int
    max_fit_body_bytes: int
    max_parse_body_bytes: int
    max_pso_work: int


class Service:
    """Store + calibration cache (thread-safe) + jobs; what the routers call."""

    CACHE_SIZE = 64

    def __init__(
        self,
        store: Store,
        jobs: Jobs,
        limits: Limits,
        token: str | Mapping[str, str] | TokenTable | None,
        *,
        sign_key: bytes | None = None,
        require_signed: bool = False,
    ):
        self.store = store
        self.sign_key = sign_key  # proves signed files (imports); what a signer signs versions with
        self.require_signed = require_signed  # only signed versions are mapped with
        self.signing = SigningPolicy(sign_key, require_signed)
        self._signed: set[tuple[int, int]] = set()  # versions proved signed (a signature never goes)
        self.jobs = jobs
        self.limits = limits
        self.auth = token is not None
        self._lock = threading.Lock()
        self._by_version: OrderedDict[tuple[int, int], Calibration] = OrderedDict()
        self._current: dict[int, tuple[int, Calibration]] = {}
        self._generation: dict[int, int] = {}
        self._image_runs: OrderedDict[str, dict] = OrderedDict()  # job id -> its detections
        self.follower: Follower | None = None  # started with the app (start_following)
        # told the id of each calibration the follower sees changed (serve: the line service's wake)
        self.change_listeners: list[Callable[[int], None]] = []

    # ------------------------------------------------------------ cache
    def cached(self, cal_id: int, version: int | None = None) -> tuple[int, Calibration] | None:
        """(version, calibration) from memory, or None (then call :meth:`calibration` off the loop)."""
        with self._lock:
            if version is None:
                hit = self._current.get(cal_id)
            else:
                cal = self._by_version.get((cal_id, version))
                hit = None if cal is None else (version, cal)
            if hit is not None and self.require_signed and (cal_id, hit[0]) not in self._signed:
                return None  # not proved signed yet: the route proves it, or refuses (served())
            return hit

    def served(self, cal_id: int, version: int | None = None) -> tuple[Version, Calibration]:
        """What a mapping request maps with: :meth:`calibration`, and with ``--require-signed`` only
        a version signed with the key (else 409 naming ``signature``, in the words every interface
        uses: :func:`~eyetohand.server.signatures.waits_for_signature`). Blocking."""
        ver, cal = self.calibration(cal_id, version)
        if self.require_signed and (cal_id, ver.version) not in self._signed:
            why = self.signing.refusal(self.store, self.store.get(cal_id).name, ver)
            if why is not None:
                raise ApiError(409, why, "signature")
            with self._lock:
                self._signed.add((cal_id, ver.version))
        return ver, cal

    def sign(self, cal_id: int, version: int) -> dict:
        """Sign ``version`` with the server's key as the acting holder (the route checked its role):
        the version's view. 409 when the server has no key or the version is signed already."""
        from eyetohand.server.storage import AlreadySigned

        ver = self.store.version(cal_id, version)
        try:
            self.signing.sign(self.store, ver)
        except AlreadySigned as exc:
            raise ApiError(409, str(exc), "version") from None
        except ValueError as exc:
            raise ApiError(409, str(exc), "sign_key") from None
        return self.out(cal_id, version)

    def calibration(self, cal_id: int, version: int | None = None) -> tuple[Version, Calibration]:
        """The stored version and its decoded calibration (decoded once, then cached). A change
        noticed while it was read (the generation moved: a write here, or the follower's report of
        one) makes it read again, so that what is cached is read after the change: kept uncached, the
        version in force was read from the store on the next request, and a store that went down then
        refused the robot (503) — the cache is what maps while the store is down. Blocking."""
        for _ in range(_READS):
            with self._lock:
                gen = self._generation.get(cal_id, 0)
            ver = self.store.version(cal_id, version)
            key = (cal_id, ver.version)
            with self._lock:
                known = self._by_version.get(key)
            where = f"calibration {cal_id} version {ver.version}"
            cal = known if known is not None else Calibration.from_dict(ver.calibration, where)
            with self._lock:
                if self._generation.get(cal_id, 0) == gen:  # no write since the read: safe to keep
                    self._by_version[key] = cal
                    self._by_version.move_to_end(key)
                    while len(self._by_version) > self.CACHE_SIZE:
                        self._by_version.popitem(last=False)
                    if version is None:
                        self._current[cal_id] = (ver.version, cal)
                    break
        return ver, cal

    def refresh(self, cal_id: int) -> None:
        """A change made elsewhere (:class:`~eyetohand.server.follow.Follower`): the cached current
        version replaced by the one now in force (read and decoded before the old one is dropped, so
        a store that fails meanwhile leaves the version in force), or every cached version dropped when
        the calibration was deleted. The generation moves first, so a request that read the store
        before the change cannot put what it read into the cache after it."""
        with self._lock:
            gen = self._generation[cal_id] = self._generation.get(cal_id, 0) + 1
            had = self._current.get(cal_id)
            pinned = had is not None or any(k[0] == cal_id for k in self._by_version)
        if not pinned:
            return  # nothing cached: the next request reads it
        now = self.store.current(cal_id)
        if now is None:
            self.invalidate(cal_id, versions_too=True)
        elif had is not None and now[1] != had[0]:
            from eyetohand.core import InputError

            ver = self.store.version(cal_id, now[1])
            try:
                cal = Calibration.from_dict(ver.calibration, f"calibration {cal_id} version {ver.version}")
            except InputError:  # unusable: dropped, so the next request reads it and says why
                self.invalidate(cal_id)
                return
            with self._lock:
                if self._generation.get(cal_id, 0) != gen:  # a write here meanwhile: it dropped its own
                    self._current.pop(cal_id, None)
                    return
                self._current[cal_id] = (ver.version, cal)
                self._by_version[(cal_id, ver.version)] = cal
                self._by_version.move_to_end((cal_id, ver.version))
                while len(self._by_version) > self.CACHE_SIZE:
                    self._by_version.popitem(last=False)

    def start_following(self, beat: Callable[[], None] | None = None) -> None:
        """Follow the store's changes (the app's start-up): see :mod:`~eyetohand.server.follow`;
        ``beat``: this server's heartbeat, called every few seconds (:mod:`~eyetohand.server.plant`)."""
        from eyetohand.server.follow import Follower

        if self.follower is None:
            self.follower = Follower(self.store, self._changed, beat=beat)
            self.follower.start()

    def _changed(self, cal_id: int) -> None:
        """What the follower reports: the listeners told first (a wake-up: cheap, never a read), then
        the cache refreshed."""
        for listener in self.change_listeners:
            listener(cal_id)
        self.refresh(cal_id)

    def store_reachable(self) -> bool | None:
        """Whether the store can be read now, as ``/api/health`` says it (None: not followed yet)."""
        return None if self.follower is None else self.follower.state.reachable

    def store_state(self) -> dict:
        """The store's state for ``/api/health``: reachable, or since when not and why."""
        if self.follower is None:
            return {"kind": self.store.dialect, "reachable": None}
        return self.follower.state.to_dict()

    def invalidate(self, cal_id: int, versions_too: bool = False) -> None:
        with self._lock:
            self._generation[cal_id] = self._generation.get(cal_id, 0) + 1
            self._current.pop(cal_id, None)
            if versions_too:
                for key in [k for k in self._by_version if k[0] == cal_id]:
                    del self._by_version[key]
                self._signed -= {k for k in self._signed if k[0] == cal_id}

    # ------------------------------------------------------------ views
    def out(
        self, cal_id: int, version: int | None = None, detail: bool = False, rec: Record | None = None
    ) -> dict:
        """The view of a version (default: the current one). ``rec``: the record a write's own
        transaction left (then ``version`` and ``current_version`` are what that write made, never
        what a concurrent write made after it); else it is read now."""
        if rec is None:
            rec = self.store.get(cal_id)
        elif version is None:
            version = rec.current_version
        ver, cal = self.calibration(cal_id, version)
        pairs = pairs_from_records(ver.pairs, source="pairs")  # every version has its pairs
        check = _pairs_of(ver.check, "check")
        excluded = ver.request.get("exclude") or []
        d = {
            "id": rec.id,
            "name": rec.name,
            "version": ver.version,
            "current_version": rec.current_version,
            "etag": rec.etag,
            "created_utc": rec.created_utc,
            "updated_utc": rec.updated_utc,
            "note": ver.note,
            "request": ver.request,
            "summary": summarize(cal, pairs, check, excluded),
            **self._signature_view(ver),
        }
        if detail:
            d.update(pairs=ver.pairs, check=ver.check, calibration=ver.calibration)
        return d

    def _signature_view(self, ver: Version) -> dict:
        """The view's ``signature`` and ``waits_for_signature`` of a version."""
        sig = self.store.signature(ver.calibration_id, ver.version)
        waits = self.require_signed and self.signing.proves(ver, sig) is not None
        return {"signature": None if sig is None else sig.to_dict(), "waits_for_signature": waits}

    def brief_list(self) -> list[dict]:
        rows = []
        for rec, ver in self.store.list():
            b = ver.brief()
            rows.append(
                {
                    "id": rec.id,
                    "name": rec.name,
                    "current_version": rec.current_version,
                    "etag": rec.etag,
                    "updated_utc": rec.updated_utc,
                    **{k: b[k] for k in ("model", "optimizer", "fitness_mm", "train_rms_mm", "check_rms_mm")},
                    # the fit record PointKind.of_fit reads (proven when stored): circle centres or not
                    "circle_diameter_mm": ver.calibration["fit"].get("target_diameter_mm"),
                }
            )
        return rows

    # ------------------------------------------------------------ writes
    def save_new(self, fitted: Fitted, name: str, note: str) -> dict:
        rec = self.store.create(
            name,
            fitted.request,
            fitted.calibration.to_dict(),
            fitted.pairs.to_records(),
            _records(fitted.check),
            note=note or "created",
        )
        return self.out(rec.id, rec=rec)

    def save_version(self, cal_id: int, fitted: Fitted, note: str, if_match: str | None = None) -> dict:
        try:
            rec = self.store.add_version(
                cal_id,
                fitted.request,
                fitted.calibration.to_dict(),
                fitted.pairs.to_records(),
                _records(fitted.check),
                note=note or "refit",
                if_match=if_match,
            )
        finally:
            self.invalidate(cal_id)
        return self.out(rec.id, rec=rec)

    def rollback(self, cal_id: int, version: int, if_match: str | None = None) -> dict:
        try:
            rec = self.store.rollback(cal_id, version, if_match=if_match)
        finally:
            self.invalidate(cal_id)
        return self.out(cal_id, rec=rec)

    def rename(self, cal_id: int, name: str, if_match: str | None = None) -> dict:
        rec = self.store.rename(cal_id, name, if_match=if_match)
        return self.out(cal_id, rec=rec)

    def delete(self, cal_id: int, if_match: str | None = None) -> None:
        try:
            self.store.delete(cal_id, if_match=if_match)
        finally:
            self.invalidate(cal_id, versions_too=True)

    def check_if_match(self, cal_id: int, if_match: str | None) -> Record:
        """The record, or :class:`~eyetohand.server.storage.Conflict` when ``if_match`` is stale (a
        quick refusal before a fit; the write checks again in its own transaction)."""
        rec = self.store.get(cal_id)
        require_match(rec, if_match)
        return rec

    def create(self, opts, name: str) -> dict:
        if self.store.by_name(name) is not None:  # before spending a fit on it
            raise ApiError(409, f"a calibration named {name!r} exists already", "name")
        return self.save_new(self.wait_fit(opts), name, "created")

    def import_calibration(
        self, name: str, calibration: dict, note: str, if_match: str | None = None
    ) -> tuple[dict, bool]:
        """Store a calibration file's JSON (proved intact first: 422 naming what is wrong) as a new
        calibration called ``name``, or as a new version of the one that has that name. Returns the
        stored calibration's view and whether it was created. A signature is checked with the key
        (422 when made with another key or not of the content) and carried by the stored version;
        an unsigned file is stored unsigned (with ``--require-signed``: not served until signed).

        Atomic: what is stored is proved to decode (exactly as every later read decodes it) before
        the one transaction that stores it; a refused file changes nothing."""
        from eyetohand.core import InputError

        try:
            cal = Calibration.from_dict(calibration, "calibration", sign_key=self.sign_key)
            body = cal.to_dict()
            Calibration.from_dict(body, "calibration")  # what the store will hand back, proved now
        except InputError as exc:
            raise ApiError(422, str(exc), _file_field(exc)) from None
        request = {
            "source": "import",
            "model": cal.model_name,
            "optimizer": cal.fit.optimizer,
            "objective": cal.fit.objective,
        }
        pairs, check = _records(cal.pairs), _records(cal.check_pairs)
        carried = self.signing.carried(body, calibration.get("signature"))  # never signed here
        rec = self.store.by_name(name)
        if rec is None:
            rec = self.store.create(
                name, request, body, pairs or [], check, note=note or "imported", signature=carried
            )
            return self.out(rec.id, rec=rec), True
        try:
            rec = self.store.add_version(
                rec.id,
                request,
                body,
                pairs or [],
                check,
                note=note or "imported",
                if_match=if_match,
                signature=carried,
            )
        finally:
            self.invalidate(rec.id)
        return self.out(rec.id, rec=rec), False

    def verify(self, cal_id: int, pairs: PointPairs, tolerance_mm: float, version: int | None = None) -> dict:
        """Verify freshly measured pairs against a stored calibration and keep the entry in its history."""
        from eyetohand.calibration import verify

        ver, cal = self.calibration(cal_id, version)
        v = verify(cal, pairs, tolerance_mm)
        entry = v.history_entry("api")
        self.store.add_verification(cal_id, ver.version, entry)
        return {**v.to_dict(), "version": ver.version}

    # ------------------------------------------------------------ jobs
    def wait_fit(self, opts: FitOptions) -> Fitted:
        job = self.jobs.fit_job(opts)
        job.done.wait()
        if job.error is not None:
            e = job.error
            raise ApiError(e.status, e.message, e.field, e.line)
        if job.fitted is None:
            raise ApiError(409, "the fit was cancelled")
        return job.fitted

    def finished_fit(self, job_id: str) -> Fitted:
        job = self.jobs.get(job_id)
        if job.kind is not JobKind.FIT:
            raise ApiError(409, f"job {job_id} is a {job.kind} job, not a fit", "id")
        if job.status != "done" or job.fitted is None:
            raise ApiError(409, f"job {job_id} is {job.status}, it has no calibration to use", "id")
        return job.fitted

    def save_job(
        self,
        job_id: str,
        name: str | None,
        calibration_id: int | None,
        note: str,
        if_match: str | None = None,
    ) -> dict:
        fitted = self.finished_fit(job_id)
        if (name is None) == (calibration_id is None):
            raise ApiError(
                422, "give either name (a new calibration) or calibration_id (a new version)", "name"
            )
        if name is not None:
            d = self.save_new(fitted, name, note)
        elif calibration_id is not None:
            d = self.save_version(calibration_id, fitted, note, if_match)
        self.jobs.get(job_id).saved = {"id": d["id"], "version": d["version"], "name": d["name"]}
        return d

    # ------------------------------------------------------------ calibration from uploaded images
    def images_job(self, req: ImagesCalibrate) -> Job:
        """Start ``calibrate-images`` on uploaded files: a job of kind "fit" (saved, followed and
        cancelled like any fit) that reads the poses CSV and detects each image on the job worker,
        with the CLI's rules and messages; :meth:`images_view` adds the per-image detections."""
        import base64
        import binascii

        if req.diameter_px is not None and not req.diameter_px > 0:
            raise ApiError(
                422, f"diameter_px: expected a positive number of px, got {req.diameter_px:g}", "diameter_px"
            )
        pso = self.jobs.check_pso_work(req.optimizer, req.particles, req.iterations)
        files: dict[str, bytes] = {}
        for i, f in enumerate([req.poses, *req.images]):
            fld = "poses" if i == 0 else f"images[{i - 1}]"
            if i and f.name in files:
                raise ApiError(422, f"{fld}.name: {f.name!r} is uploaded twice", f"{fld}.name")
            try:
                data = base64.b64decode(f.data_base64, validate=True)
            except (binascii.Error, ValueError):
                raise ApiError(422, f"{fld}.data_base64: not base64 text", f"{fld}.data_base64") from None
            if i == 0:
                poses_bytes = data
            else:
                files[f.name] = data
        run: dict = {"poses": 0, "detections": [], "left_out": [], "unused_images": []}

        def work(job: Job) -> None:
            _images_work(job, req, poses_bytes, files, run)

        job = self.jobs.submit(JobKind.FIT, work, req.iterations if pso else 0)
        with self._lock:
            self._image_runs[job.id] = run
            while len(self._image_runs) > self.jobs.keep:
                self._image_runs.popitem(last=False)
        return job

    def images_view(self, job_id: str, since: int = 0) -> dict:
        job = self.jobs.get(job_id)
        with self._lock:
            run = self._image_runs.get(job_id)
        if run is None:
            raise ApiError(404, f"job {job_id} is not a calibration from images", "id")
        return {
            **job.view(since),
            "poses": run["poses"],
            "detections": list(run["detections"]),
            "left_out": list(run["left_out"]),
            "unused_images": list(run["unused_images"]),
            "pairs": job.fitted.pairs.to_records() if (job.fitted and job.status == "done") else None,
        }

    def close(self) -> None:
        if self.follower is not None:
            self.follower.stop()
        self.jobs.shutdown()
        self.store.close()


def _images_work(job: Job, req: ImagesCalibrate, poses_bytes: bytes, files: dict[str, bytes], run: dict):
    """The job: the upload written to a private temporary folder, then exactly what
    ``eyetohand calibrate-images POSES.csv`` does there (messages name the files as uploaded)."""
    import os
    import tempfile
    from pathlib import Path

    from eyetohand.core import InputError
    from eyetohand.server.schemas import PairIn
    from eyetohand.vision import ImageResult, detect_poses, load_poses, pairs_from_detections

    opts: dict = {"polarity": req.polarity}
    if req.diameter_px is not None:
        opts["diameter_px"] = req.diameter_px
    with tempfile.TemporaryDirectory(prefix="eyetohand-images-") as tmp:
        root = Path(tmp).resolve()
        prefix = str(root) + os.sep

        def fail(exc: InputError, fld: str) -> ApiError:
            return ApiError(422, str(exc).replace(prefix, ""), fld, exc.line)

        poses_path = root / req.poses.name
        poses_path.write_bytes(poses_bytes)
        job.phase = f"reading {req.poses.name}"
        try:
            poses = load_poses(poses_path, root)
        except InputError as exc:
            raise fail(exc, "poses") from None
        run["poses"] = len(poses)
        named = set()
        results: list[ImageResult] = []
        for i, pose in enumerate(poses):
            if job.cancel.is_set():
                return
            job.phase = f"detecting the target: image {i + 1} of {len(poses)} ({pose.image})"
            job.step("images", i, len(poses))
            base = pose.image.replace("\\", "/").rsplit("/", 1)[-1]
            upload = base if base in files else None
            inside = pose.path.resolve().is_relative_to(root) and not Path(pose.image).is_absolute()
            if upload is None or not inside:
                res = ImageResult(
                    pose.image, False, reason=f"{pose.image}: no such file among the uploaded images"
                )
            else:
                named.add(upload)
                pose.path.parent.mkdir(parents=True, exist_ok=True)
                pose.path.write_bytes(files[upload])
                res = detect_poses([pose], **opts)[0]
                pose.path.unlink()
            results.append(res)
            run["detections"].append(res.to_dict())
            if not res.ok:
                run["left_out"].append(res.image)
        job.step("images", len(poses), len(poses))
        run["unused_images"] = sorted(set(files) - named)
        try:
            pairs = pairs_from_detections(poses, results, req.poses.name)
        except InputError as exc:
            raise fail(exc, "images") from None
    records = [
        PairIn.model_construct(
            id=pid, u=float(uv[0]), v=float(uv[1]), x=float(p[0]), y=float(p[1]), z=float(p[2])
        )
        for pid, uv, p in zip(pairs.ids, pairs.uv_px, pairs.xyz_mm, strict=True)
    ]
    fit_opts = FitOptions.model_construct(
        pairs=records,
        check=req.check,
        model=req.model,
        optimizer=req.optimizer,
        objective=req.objective,
        seed=req.seed,
        exclude=[],
        particles=req.particles,
        iterations=req.iterations,
        image_size=req.image_size,
        target_diameter_mm=req.target_diameter_mm,
    )
    fitted = fit(fit_opts, fit_progress(job, req.model, req.optimizer, req.iterations))
    fitted.request.update(
        source="images",
        poses=req.poses.name,
        polarity=req.polarity,
        diameter_px=req.diameter_px,
        left_out=list(run["left_out"]),
    )
    finish_fit(job, fitted, req.optimizer)


def _file_field(exc) -> str:
    """The request field a calibration file's refusal names: ``calibration.<field>`` when the words
    name one (``field 'schema_version' …``), else ``calibration``."""
    import re

    m = re.search(r"field '([^']+)'", str(exc))
    return f"calibration.{m.group(1)}" if m else "calibration"


def _pairs_of(records: list[dict] | None, label: str) -> PointPairs | None:
    return None if records is None else pairs_from_records(records, source=label)


def _records(p: PointPairs | None) -> list[dict] | None:
    return None if p is None else p.to_records()


__all__ = ["Service", "Limits", "Record"]
