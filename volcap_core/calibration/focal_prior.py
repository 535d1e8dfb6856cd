"""A lens calibration's focal held unless the footage shows it wrong.

A camera whose rig carries measured intrinsics (a checkerboard lens calibration, good to a fraction
of a percent) and a camera with only its lens metadata (a nominal focal, good to a few percent) need
different focal priors in the static adjustments. The loose prior (``BundleOptions.focal_sigma_rel``,
3 %) lets two converging views trade a common zoom against their convergence: on Pose2Sim's cam01 /
cam02 the held lens calibration moved by 1.3-1.7 % rms over reference frames, with nothing in the
footage to say so (docs/calibration.md, "Focal drift from a held lens calibration"). A tight prior
alone would hold a lens calibration that is wrong (a rig typed with the wrong lens, or a
calibration from another unit) against footage that shows it.

So a measured focal needs evidence to move (:func:`adjust_with_held_focals`):

1. the adjustment with every measured focal pinned at its lens calibration (a prior of
   :data:`PINNED_SIGMA_REL`) and the nominal ones under the loose prior, and the same adjustment
   with the loose prior on every focal: the two hypotheses, "the lens calibration's focal is right"
   and "the footage sets it";
2. each measured camera's evidence: how much better its own observations fit with its focal free,
   ``Δχ² = Σ ρ(r_pinned / s) - ρ(r_free / s)`` over the observations both kept (``ρ(x²) = log(1 +
   x²)``, the adjustments' Cauchy cost, ``x²`` for small residuals; ``s`` the free adjustment's
   residual spread per coordinate, so that ``Δχ²`` counts observations at what they show, not at
   the 1 px weighting). A tight prior would not do for the first hypothesis: against thousands of
   observations a 0.5 % prior gives way by most of a 3 % error, and the fit hides the evidence;
3. the cameras whose ``Δχ²`` exceeds ``release_chi2`` are released (their focals take the loose
   prior), the strongest first (at least half the largest evidence): a wrong focal also worsens the
   fit of the cameras that share its points, so steps 1-3 run again with the released focals free
   until no held camera's evidence exceeds ``release_chi2``. The others are held: their focal under the tight prior (``tight_sigma_rel``, default 0.5 %, a
   checkerboard calibration's precision), so that strong footage may still correct it by a
   fraction of a percent. The final adjustment runs with those priors (the free one is the answer
   when every measured camera is released).

``release_chi2`` (25, a χ²₁ tail of 1e-6) is well above a χ²₁ test's 10.8 at 0.001: the
observations of one camera are not independent (one lens's residual field, the shared points), and
stated sigmas on real footage have been ~2x small. Measured figures: docs/calibration.md, "A
measured focal needs evidence to move".
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np

from volcap_core.calibration.bundle import BundleResult

#: the prior (1σ, relative) of a measured focal while it is held: a checkerboard lens
#: calibration's precision
MEASURED_FOCAL_SIGMA_REL = 0.005
#: the prior (1σ, relative) that pins a measured focal for the evidence test: its move is then
#: ~1e-4 of what the footage would do with it free
PINNED_SIGMA_REL = 1e-4
#: a measured focal is released when its camera's observations fit better by more than this
#: (Δχ² at the residuals' spread; docs/calibration.md, "A measured focal needs evidence to move")
RELEASE_CHI2 = 25.0


@dataclass(frozen=True)
class FocalDecision:
    """What :func:`adjust_with_held_focals` did with one measured camera's focal and why."""

    #: True: the focal kept the tight prior (no evidence); False: released to the loose prior
    held: bool
    #: how much better the camera's observations fit with its focal free (Δχ², module docstring)
    evidence_chi2: float
    #: the focal's move from its measured value in the final adjustment, and with the loose prior
    #: (relative, of the log focal)
    shift_rel: float
    free_shift_rel: float
    #: the release threshold it was held to
    release_chi2: float

    def as_stats(self) -> dict[str, float]:
        """The figures a record's numeric stats and a camera's quality can carry."""
        return {"focal_held": float(self.held), "focal_evidence_chi2": self.evidence_chi2,
                "focal_shift_pct": 100 * self.shift_rel, "focal_free_shift_pct": 100 * self.free_shift_rel,
                "focal_release_chi2": self.release_chi2}


def evidence_chi2(pinned: BundleResult, free: BundleResult, obs_camera: np.ndarray, ncam: int) -> np.ndarray:
    """Each camera's Δχ² [C] between two adjustments of the same observations (``obs_camera`` [M],
    the order both results' ``reprojection_px`` and ``inlier`` are in): the Cauchy cost of its
    observations kept by both, ``pinned`` minus ``free``, at ``free``'s residual spread per coordinate
    (the median reprojection error / 1.1774, a 2-D Gaussian's median radius; at least 0.05 px)."""
    both = pinned.inlier & free.inlier
    r_free = free.reprojection_px[free.inlier]
    s = max(float(np.median(r_free)) / 1.1774 if len(r_free) else 1.0, 0.05)
    drop = np.log1p((pinned.reprojection_px / s) ** 2) - np.log1p((free.reprojection_px / s) ** 2)
    return np.bincount(np.asarray(obs_camera)[both], weights=drop[both], minlength=ncam)[:ncam]


def adjust_with_held_focals(adjust: Callable[[np.ndarray], BundleResult], measured: Sequence[bool],
                            focal_prior: np.ndarray, obs_camera: np.ndarray, *, loose_sigma_rel: float,
                            tight_sigma_rel: float | None = MEASURED_FOCAL_SIGMA_REL,
                            release_chi2: float = RELEASE_CHI2, focal_of: np.ndarray | None = None
                            ) -> tuple[BundleResult, dict[int, FocalDecision]]:
    """Adjust cameras whose focals are measured (``measured`` [C]) holding those focals unless the
    footage shows them wrong (module docstring). ``adjust(focal_sigma)`` runs the adjustment with
    each camera's focal prior sigma ``focal_sigma`` [C] (relative) and returns its result;
    ``focal_prior`` [C] px the focals' priors; ``obs_camera`` [M] the camera of each observation
    the adjustment is given. ``focal_of`` [C]: the focal unknown of each camera when cameras share
    one (a lens group's, ``bundle.camera_parameters``): a shared focal is held or released as one,
    on its cameras' summed evidence.

    Returns the adjustment taken and, per measured camera index, its :class:`FocalDecision`.
    Without a measured camera, or with ``tight_sigma_rel`` None, the single loose adjustment and
    no decisions: the nominal cameras' prior is unchanged."""
    measured = np.asarray(measured, bool)
    ncam = len(measured)
    loose = np.full(ncam, loose_sigma_rel)
    if tight_sigma_rel is None or not measured.any():
        return adjust(loose), {}
    free = adjust(loose)
    of = np.arange(ncam) if focal_of is None else np.asarray(focal_of)
    keep = measured.copy()
    evidence = np.zeros(ncam)
    while keep.any():
        pinned = adjust(np.where(keep, PINNED_SIGMA_REL, loose_sigma_rel))
        chi2 = np.bincount(of, weights=evidence_chi2(pinned, free, obs_camera, ncam))[of]
        evidence[keep] = chi2[keep]
        strong = keep & (chi2 > release_chi2)
        if not strong.any():
            break
        # the strongest first: a wrong focal also worsens the fit of the cameras sharing its points,
        # so those are tested again with it released
        keep &= ~(strong & (chi2 >= 0.5 * chi2[keep].max()))
    final = free if not keep.any() else adjust(np.where(keep, tight_sigma_rel, loose_sigma_rel))
    prior = np.asarray(focal_prior, np.float64)
    return final, {i: FocalDecision(held=bool(keep[i]), evidence_chi2=float(evidence[i]),
                                    shift_rel=float(np.log(final.focal[i] / prior[i])),
                                    free_shift_rel=float(np.log(free.focal[i] / prior[i])),
                                    release_chi2=release_chi2)
                   for i in range(ncam) if measured[i]}
