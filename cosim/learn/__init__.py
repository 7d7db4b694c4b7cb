"""``cosim learn``: a small PointPillars-style BEV detector trained on cosim episodes (docs/learnability.md).

Layout: :mod:`cosim.learn.grid` (numpy voxeliser, training targets, box decoding), :mod:`cosim.learn.nms`
(circle NMS in numpy), :mod:`cosim.learn.data` (samples through :mod:`cosim.io.dataset`, fusion modes),
:mod:`cosim.learn.model` and :mod:`cosim.learn.train` (PyTorch). Only the last two import torch, which
comes with the optional extra ``pip install -e '.[learn]'``; the rest of cosim never imports it.
"""

from __future__ import annotations

from cosim.errors import InputError

INSTALL_HINT = "pip install -e '.[learn]'"


def require_torch():
    """The ``torch`` module, or one :class:`InputError` saying how to install it."""
    try:
        import torch
    except ModuleNotFoundError as exc:
        if exc.name != "torch":
            raise
        raise InputError(f"cosim learn needs PyTorch, which is not installed: {INSTALL_HINT} "
                         "(the optional extra 'learn')") from None
    return torch
