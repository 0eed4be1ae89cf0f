"""OpenCV's contrib Gray-code generator for a machine whose OpenCV lacks the contrib modules.

The GPU machines' image ships ``opencv-python-headless`` without ``cv2.structured_light``, and the
contrib wheel is too large to carry there beside the working tree. Put this folder on ``PYTHONPATH``
(``benchmarks/cuda_checks.sh`` says how) and Python imports it at start-up: where ``cv2`` has no
``structured_light``, it gets a ``GrayCodePattern`` whose ``generate()`` gives OpenCV's sequence
(columns then rows, most significant bit first, each pattern followed by its inverse);
``tests/calib/test_graycode.py`` checks it against OpenCV's own. Nothing else of OpenCV is replaced.
"""

import types

import numpy as np

try:
    import cv2
except ImportError:  # no OpenCV at all: nothing to complete
    cv2 = None


class GrayCodePattern:
    def __init__(self, width: int, height: int):
        self.width, self.height = width, height

    @classmethod
    def create(cls, width: int, height: int) -> "GrayCodePattern":
        return cls(width, height)

    def generate(self) -> tuple[bool, list[np.ndarray]]:
        out = []
        for size, along_x in ((self.width, True), (self.height, False)):
            index = np.arange(size)
            gray = index ^ (index >> 1)
            for bit in range(int(np.ceil(np.log2(size))) - 1, -1, -1):
                line = ((gray >> bit) & 1).astype(np.uint8) * 255
                image = np.broadcast_to(line[None, :] if along_x else line[:, None], (self.height, self.width)).copy()
                out += [image, 255 - image]
        return True, out


if cv2 is not None and not hasattr(cv2, "structured_light"):
    cv2.structured_light = types.SimpleNamespace(GrayCodePattern=GrayCodePattern)
