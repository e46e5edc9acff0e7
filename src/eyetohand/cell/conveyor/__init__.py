"""Conveyor tracking: the camera sees a part upstream, the robot picks it downstream on the moving belt.

The model (robot frame, mm; see ``docs/conveyor.md``):

* An **encoder** counts belt motion in a signed or unsigned counter of ``width_bits`` bits that rolls
  over. The difference of two readings is the *shortest signed difference modulo the counter's range*
  (:meth:`Encoder.delta`): correct whenever the belt moved less than half the range between them
  (2²³ counts for 24 bits — 168 m at 0.02 mm/count), and a small backward jitter stays a small
  negative number instead of turning into a near-full-range jump, so that it can be detected.
* The **belt** carries parts along a unit ``direction`` (downstream, robot frame; not necessarily along
  a robot axis, not necessarily level) by ``mm_per_count`` mm per count, with a sign: negative when the
  counts fall as the belt runs downstream. ``b = direction · mm_per_count`` is the *belt vector*.
* A part seen at pixel ``uv`` in an image whose latched count is ``e_image`` is, when the encoder reads
  ``e_now``, at ``p(uv) + b · (delta(e_image, e_now) + latch)``, where ``p(uv)`` is the camera's
  image → robot map for parts on the belt (x, y from an eyetohand :class:`Calibration`, z from the
  plane of the parts' tops ``z = c0 + c1 (x − x0) + c2 (y − y0)``) and ``latch`` the counts by which
  the image's latched count runs *ahead* of its exposure (0 unless calibrated).

Calibrating it (:func:`calibrate_conveyor`): every touch of a sighted part gives three equations
``p(uv_s) + b · (Δe + latch · moving_s) = xyz_touch``; every touch of a part touched at two or more
counts without a sighting (the Omron/Adept belt recipe) gives ``P_k + b · Δe = xyz_touch`` with the
part's position ``P_k`` unknown; every further sighting ``s`` of a part (first sighted at ``a``) gives
``p(uv_a) + b · (Δe(a→s) + latch · (m_a − m_s)) = p(uv_s)`` — the latch contrast within one part,
where the touches' errors cancel, when one frame was taken with the belt stopped and one running. The
camera map's parameters, the belt vector, the surface plane, the
latch delay and the unseen parts' positions are fitted jointly (``scipy.optimize.least_squares`` on
the batched forward map); the covariance of every estimate is the cluster-robust sandwich at the
solution (:mod:`.fit`: the touches and further sightings of one part share its first
sighting's errors), never
below ``s² (JᵀJ)⁻¹`` with ``s²`` the residual variance. :func:`calibrate_belt` is the belt-only recipe.

The report (:class:`~eyetohand.cell.conveyor.report.ConveyorReport`, kept in the calibration as its JSON
record) separates the error sources and names the faults it finds, each by a statistical test with the
threshold stated in :data:`THRESHOLDS`.

The modules: :mod:`.records` (encoder, belt, session), :mod:`.file` (the calibrated conveyor, its
mapping and its file), :mod:`.fit` (the joint fit), :mod:`.report` (the report).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from eyetohand.core import lazy_exports

if TYPE_CHECKING:
    from eyetohand.cell.conveyor.file import ConveyorCalibration
    from eyetohand.cell.conveyor.fit import calibrate_belt, calibrate_conveyor
    from eyetohand.cell.conveyor.records import (
        Belt,
        Encoder,
        Session,
        direction_from_angles,
        load_session,
        session_from_text,
    )
    from eyetohand.cell.conveyor.report import THRESHOLDS, format_report
else:
    __getattr__, __dir__ = lazy_exports(
        __name__,
        {
            "file": ("ConveyorCalibration",),
            "fit": ("calibrate_belt", "calibrate_conveyor"),
            "records": (
                "Belt",
                "Encoder",
                "Session",
                "direction_from_angles",
                "load_session",
                "session_from_text",
            ),
            "report": ("THRESHOLDS", "format_report"),
        },
    )

__all__ = [
    "Belt",
    "ConveyorCalibration",
    "Encoder",
    "Session",
    "THRESHOLDS",
    "calibrate_belt",
    "calibrate_conveyor",
    "direction_from_angles",
    "format_report",
    "load_session",
    "session_from_text",
]
