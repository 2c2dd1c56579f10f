"""What was observed: the target images and how to read them (one :class:`Observations`), and
how they are fitted (a :class:`Strategy`: :class:`VarPro` or :class:`Optimistix`).

Both are frozen dataclasses whose values are checked on the host when they are made, with
messages naming the field."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
from jaxtyping import ArrayLike, Float

import diffshade as ds

from ._domains import check_fit

SOLVERS = ("lm", "dogleg", "gauss-newton")  # optimistix's least-squares solvers (fitting._optimistix)


class FitError(ValueError):
    """Observations that do not match the scene (size, channels, count), or a bad fit option."""


def as_list(targets) -> list:
    """One image or a list of images, as a list."""
    return [targets] if hasattr(targets, "shape") else list(targets)


#: ``Observations.clip_margin`` of a photometric capture (``diffshade fit FOLDER``): 1 pixel at the
#: fitted resolution (a study of a real capture found two thirds of a Blinn-Phong fit's excess
#: within 1-3 full-resolution pixels of clipped highlight cores; docs/photographs.md).
CAPTURE_CLIP_MARGIN = 1

#: ``Observations.margin`` of a photometric capture: 1 pixel. A camera integrates over each pixel,
#: so the silhouette's pixels are mixed with the background; a mask keeps them (measured on
#: captures whose rim pixels are their coverage times the shading: every masked pixel fitted,
#: 21.9x the noise at 32² and rejected; margin 1, the truth to 3e-6; docs/photographs.md).
CAPTURE_MARGIN = 1


@dataclass(frozen=True, eq=False)
class Observations:
    """The target images of a fit and how to read them.

    - ``targets``: one ``[H, W, 3]`` image or a sequence, one per view;
    - ``views``: the scenes of the views (same structure; they differ in camera, lights, ...),
      default the fitted scene for every target;
    - ``masks``: optional per-view ``[H, W]`` weights (0: not fitted);
    - ``encoding``: None (the targets are linear values), or how they are encoded (``"srgb"``,
      ``"gamma:G"``, ``"linear"``; one, or one per target): they are then code values in
      [0, 1], decoded to linear values, clipping decided on the codes, and each residual weighted
      by :math:`1/(dL/dv)`, so that the fit measures it in code values (``noise`` too);
    - ``saturation``: the level at which the camera clipped (1.0 for images read from 8- or
      16-bit files): a channel at or above it is censored (one-sided residual), and so is one at 0;
    - ``quantum``: the code step of an integer target (1/255, 1/65535), for the noise floor;
    - ``noise``: the noise level σ if known (else estimated from the residual);
    - ``margin``: pixels within this many 8-neighbour steps of the model's silhouette, of an
      occlusion edge or of a mask's edge are left out of the fit;
    - ``clipped``: optional per-view ``[H, W]`` or ``[H, W, 3]`` booleans, the entries known to
      be clipped whatever their value (a pixel averaged from sub-pixels of which one was
      clipped: :func:`fitting.downsample`): censored from above like those at ``saturation``,
      each a lower bound at its own value;
    - ``clip_margin``: the entries within this many 8-neighbour steps of a pixel censored from
      above (any channel) are left out of the fit, the pixel's own unclipped channels too: a real
      camera's clipped highlight bleeds into the pixels around it (bloom, smear), which then read
      brighter than the scene; of the clipped entries only those this far inside their clipped
      region stay, censored (at its rim the neighbours' bloom may be what clipped them). 0 (the default) for renders; a photometric capture
      is read with :data:`fitting.CAPTURE_CLIP_MARGIN` (and ``margin`` :data:`fitting.CAPTURE_MARGIN`);
    - ``noise_model``: ``"uniform"`` (the default: every entry's noise the same) or ``"level"``:
      the variance rises with the level, :math:`\\sigma^2 = a + b\\,m` per channel (read noise and
      photon noise), :math:`a, b` estimated from the targets (:mod:`fitting._noise`), and each
      residual entry weighted by :math:`\\bar\\sigma/\\sigma(m)` at the model's level :math:`m`
      (re-taken at the model, like an encoded target's weights: iteratively reweighted least
      squares), :math:`\\bar\\sigma` the noise level the verdict compares with.
    """

    targets: Sequence[Float[ArrayLike, "H W 3"]]
    views: Sequence[ds.Scene] | None = None
    masks: Sequence[Float[ArrayLike, "H W"] | None] | None = None
    encoding: str | Sequence[str | None] | None = None
    saturation: float | None = None
    quantum: float | None = None
    noise: float | None = None
    margin: int = 0
    clipped: Sequence[ArrayLike | None] | None = None
    clip_margin: int = 0
    noise_model: str = "uniform"

    def __post_init__(self):
        targets = tuple(as_list(self.targets))
        object.__setattr__(self, "targets", targets)
        n = len(targets)
        if not n:
            raise FitError("targets: no target image")
        if self.views is not None:
            object.__setattr__(self, "views", tuple(self.views))
            if len(self.views) != n:
                raise FitError(f"{n} targets but {len(self.views)} views")
        if self.masks is not None:
            object.__setattr__(self, "masks", tuple(self.masks))
            if len(self.masks) != n:
                raise FitError(f"{n} targets but {len(self.masks)} masks")
        if self.clipped is not None:
            object.__setattr__(self, "clipped", tuple(self.clipped))
            if len(self.clipped) != n:
                raise FitError(f"{n} targets but {len(self.clipped)} clipped masks")
        if len(self.encodings) != n:
            raise FitError(f"{n} targets but {len(self.encodings)} encodings")
        for name in ("margin", "clip_margin", "saturation", "quantum", "noise"):
            check_fit("Observations", name, getattr(self, name), FitError)
        if self.noise_model not in NOISE_MODELS:
            raise FitError(
                f"Observations.noise_model must be one of {', '.join(NOISE_MODELS)}, got {self.noise_model!r}"
            )

    @property
    def encodings(self) -> list:
        """One encoding per target (None: linear)."""
        if isinstance(self.encoding, (list, tuple)):
            return list(self.encoding)
        return [self.encoding] * len(self.targets)

    def views_of(self, scene: ds.Scene) -> list[ds.Scene]:
        """The views' scenes, ``scene`` for each where none were given."""
        return list(self.views) if self.views is not None else [scene] * len(self.targets)

    def replace(self, **changes) -> Observations:
        return dataclasses.replace(self, **changes)


#: The noise models of :class:`Observations` (``noise_model``).
NOISE_MODELS = ("uniform", "level")


@dataclass(frozen=True)
class Strategy:
    """How a fit is solved, whichever solver moves the nonlinear parameters.

    - ``starts``: the size of the global start (the given start and Halton points over each
      nonlinear parameter's plausible range), ranked when the given start's result is rejected;
    - ``restarts``: how many further starts are tried when the verdict rejects a result;
    - ``max_steps``: the solver's step limit; ``polish_steps``: the float64 polish's;
    - ``rtol``: the solver's relative tolerance (None: 1e-6 in float32, 1e-10 in float64);
    - ``method``: ``"auto"`` (variable projection where the image is linear) or ``"full"``
      (Levenberg–Marquardt on every parameter);
    - ``visibility_passes``: with a free camera pose, how many times the fit is repeated with the
      visibility rasterised again (see :func:`fitting.fit`);
    - ``verbose``: print every solver step.
    """

    starts: int = 64
    restarts: int = 3
    max_steps: int = 100
    polish_steps: int = 20
    rtol: float | None = None
    method: Literal["auto", "full"] = "auto"
    visibility_passes: int = 6
    verbose: bool = False

    def __post_init__(self):
        if self.method not in ("auto", "full"):
            raise FitError(f"unknown method {self.method!r}; 'auto' or 'full'")
        for name in ("starts", "restarts", "max_steps", "polish_steps", "visibility_passes", "rtol"):
            check_fit(type(self).__name__, name, getattr(self, name), FitError)
        if not isinstance(self.verbose, bool):
            raise FitError(f"{type(self).__name__}.verbose must be True or False, got {self.verbose!r}")

    def tolerance(self, dtype) -> float:
        """The default tolerance of the float type: 1e-6 in float32, 1e-10 in float64."""
        return 1e-6 if np.dtype(dtype) == np.float32 else 1e-10

    def replace(self, **changes) -> Strategy:
        return dataclasses.replace(self, **changes)


@dataclass(frozen=True)
class VarPro(Strategy):
    """Variable projection (the default): the parameters the image is linear in solved exactly
    under their bounds at every step, Levenberg–Marquardt on the others, in one compiled program
    (:mod:`fitting._varpro`); then the float64 polish and, with intervals, the scan for other
    basins."""


@dataclass(frozen=True)
class Optimistix(Strategy):
    """optimistix's ``solver`` (``"lm"``, ``"dogleg"``, ``"gauss-newton"``) on the same reduced
    problem, from the best of the global start's candidates ranked on a pixel subset; then the
    polish on the whole image. ``atol``: its absolute tolerance (None: as ``rtol``'s default)."""

    solver: Literal["lm", "dogleg", "gauss-newton"] = "lm"
    atol: float | None = None

    def __post_init__(self):
        super().__post_init__()
        if self.solver not in SOLVERS:
            raise FitError(f"unknown solver {self.solver!r}; one of {sorted(SOLVERS)}")
        check_fit("Optimistix", "atol", self.atol, FitError)
