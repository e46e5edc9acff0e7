"""Find the target's solid circle in an image, with sub-pixel accuracy.

Three stages:

1. **Candidates** on a downscaled copy (area averaging, so a 2448×2048 image is searched at 612×512):
   the image is cut at up to 20 grey levels (10 spread between its darkest and brightest pixel, 10
   between its 0.5th and 99.5th percentiles); at each level the connected dark (and bright) regions
   are kept when they are big enough, fill their bounding box like an ellipse, have no hole (solid),
   keep off the image border, are round once their second moments are whitened, and stand out from
   the ring around them by at least 6 noise σ. A region found at two or more levels in the same place
   is a candidate. Uneven light only moves the levels at which a region appears, not whether it
   does. Only windows around what the same search with looser bounds (and every other level) finds
   on a copy downscaled 2× more are labelled (the whole image when that finds nothing, or when the
   windows give no circle).
2. **Edge points** at full resolution around each candidate: the image is sampled (bilinear) along
   one radial profile per boundary pixel, from inside to outside the candidate's ellipse; each
   profile's edge is the centroid of its gradient above a quarter of its peak (exact for a
   symmetrically blurred edge, whatever the blur). An ellipse is fitted to the edge points (normalised
   algebraic conic, then points farther than 3.5 robust σ from it dropped), and the profiles are cast
   again from the new centre. This ellipse decides whether the candidate is a circle (share of usable
   profiles, rms distance of the edge points).
3. **Intensity model** (``refine="intensity"``, the default): the pixels within a few px of that
   ellipse's edge are fitted with a blurred solid ellipse under smooth light,
   ``I = (1 + gx·x + gy·y) · (a_in + (a_out(φ) − a_in) · Φ(d / s))`` — ``d`` the signed distance from
   the ellipse, ``Φ`` the normal CDF, ``s`` the edge spread (blur and pixel), ``a_out(φ)`` the outer
   level with 4 angular harmonics — by robust (soft-L1) least squares over the 18 parameters
   (Levenberg–Marquardt on the 18 × 18 normal equations, analytic Jacobian). It uses every pixel of
   the edge band at its own noise (the edge points average differentiated, interpolated samples),
   which halves the error on the benchmark's renders; a fit that fails or moves more than 0.5 px from
   the edge points' ellipse is dropped and that ellipse kept (``Detection.method`` says which). The
   centre reported is the fitted ellipse's: the centre of the *imaged ellipse*, not the image of the
   circle's centre — they differ by the perspective bias of a tilted view (see
   :mod:`eyetohand.vision.render`).

Everything is vectorised over profiles and samples. ``detect_target`` wants exactly one circle; it
refuses (``ok=False`` with a ``reason``, never a guessed centre) when there is none, when two or more
candidates are equally good, or when the circle is cut by the image border. ``detect_circles`` returns
every circle (dot grids). Files that cannot be read as images raise
:class:`~eyetohand.core.errors.InputError`.

The modules: :mod:`.read` (the image and its noise σ), :mod:`.search` (stage 1), :mod:`.refine`
(stages 2 and 3), :mod:`.quality` (the :class:`Detection` record, its score and the refusals) and
:mod:`.api` (:func:`detect_target`, :func:`detect_circles` and :func:`annotate`, which run them).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from eyetohand.core import lazy_exports

if TYPE_CHECKING:
    from eyetohand.vision.detect.api import annotate, detect_circles, detect_target
    from eyetohand.vision.detect.quality import Detection, Miss
    from eyetohand.vision.detect.read import check_complete, load_image, noise_sigma
    from eyetohand.vision.detect.refine import fit_ellipse
else:
    __getattr__, __dir__ = lazy_exports(
        __name__,
        {
            "api": ("annotate", "detect_circles", "detect_target"),
            "quality": ("Detection", "Miss"),
            "read": ("check_complete", "load_image", "noise_sigma"),
            "refine": ("fit_ellipse",),
        },
    )

__all__ = [
    "Detection",
    "Miss",
    "annotate",
    "check_complete",
    "detect_circles",
    "detect_target",
    "fit_ellipse",
    "load_image",
    "noise_sigma",
]
