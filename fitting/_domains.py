"""The domain of every option of a fit, in the library and on the command line: one table.

:data:`FIT` holds the numbers :class:`fitting.Observations`, :class:`fitting.VarPro` /
:class:`fitting.Optimistix` and :func:`fitting.fit` take; :data:`CLI` says which of them each
numeric option of ``diffshade fit`` and ``diffshade demo`` is (and the demo's own). Both are
checked with :func:`diffshade._domains.check` (the scene's numbers: :data:`diffshade._domains.SCENE`),
so a message names the option as the user wrote it and the allowed range, and the command line
exits 3 before it reads an image or writes a file.
"""

from __future__ import annotations

import dataclasses

from diffshade._domains import Domain, check

WHOLE = Domain(kind="int", lo=0)
COUNT = Domain(kind="int", lo=1)
SIGMA = Domain(lo=0.0, lo_open=True, optional=True)

#: Every numeric option of a fit, by its name in the library.
FIT: dict[str, Domain] = {
    # Observations
    "noise": SIGMA,
    "saturation": SIGMA,
    "quantum": Domain(lo=0.0, hi=1.0, lo_open=True, optional=True),
    "margin": WHOLE,
    "clip_margin": WHOLE,
    # Strategy (VarPro, Optimistix)
    "starts": COUNT,
    "restarts": WHOLE,
    "max_steps": COUNT,
    "polish_steps": WHOLE,
    "visibility_passes": COUNT,
    "rtol": Domain(lo=0.0, hi=1.0, lo_open=True, hi_open=True, optional=True),
    "atol": SIGMA,
    # fit()
    "albedo_smoothness": Domain(lo=0.0),
}

#: The command line's numeric options: ``--option`` -> (its ``args`` attribute, its domain).
CLI: dict[str, tuple[str, Domain]] = {
    "--noise": ("noise", FIT["noise"]),
    "--max-steps": ("max_steps", FIT["max_steps"]),
    "--margin": ("margin", FIT["margin"]),
    "--clip-margin": ("clip_margin", FIT["clip_margin"]),
    "--holdout": ("holdout", Domain(kind="int", lo=2)),  # fit: every K-th view held out
    "--albedo-smoothness": ("albedo_smoothness", FIT["albedo_smoothness"]),
    "--size": ("size", Domain(kind="int", lo=8, hi=4096)),  # demo: the image side
    "--seed": ("seed", WHOLE),  # demo: the perturbed start's seed
    "--downsample": ("downsample", Domain(kind="int", lo=1, hi=64)),  # fit: a photometric capture's factor
}


def check_fit(owner: str, name: str, value, error: type[Exception]):
    """``value`` if it lies in ``FIT[name]``, else ``error`` naming ``owner.name`` and the range."""
    return check(f"{owner}.{name}" if owner else name, value, FIT[name], error)


def check_args(args, error: type[Exception]) -> None:
    """Every numeric option the parsed command line ``args`` has, by :data:`CLI`: read from its
    text (the parser leaves it a string, so that "abc" is this error too, not a usage error) and
    held to its domain; ``args`` then holds the numbers."""
    for option, (attr, dom) in CLI.items():
        raw = getattr(args, attr, None)
        if raw is None:
            continue
        dom = dataclasses.replace(dom, optional=False)  # given: a number
        try:
            value = (int if dom.kind == "int" else float)(raw)
        except ValueError:
            raise error(f"{option} must be {dom.describe()}, got {raw!r}") from None
        setattr(args, attr, check(option, value, dom, error))
