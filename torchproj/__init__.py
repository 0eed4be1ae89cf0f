"""torchproj: multi-projector depth-dependent projection in PyTorch.

Rooms, in the order data flows: :mod:`torchproj.scene` (rig descriptions), :mod:`torchproj.sim`
(the virtual rig), :mod:`torchproj.calib` (Gray code, response fit, triangulation). Shared pieces
live in :mod:`torchproj.core`; conventions are stated once in :mod:`torchproj.core.conventions`.
"""

__version__ = "0.1.0"

__all__ = ["__version__"]
