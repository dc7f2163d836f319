"""OpenCV that gives the same pixels on every x86-64 CPU: Intel's IPP off in the calling thread.

OpenCV hands some of pidc's calls (``cv2.blur``, ``cv2.remap``, ``cv2.resize``) to Intel's IPP, which picks its own
kernels by CPU (SSE4.2 ``y8``, AVX2 ``l9``, AVX-512 ``k0``, …) and rounds unlike OpenCV's own code. Measured on an AMD
EPYC (IPP's AVX2 kernels): with IPP off, 1 of the pipeline's first 200 test images changed by one level in one pixel,
so which kernels IPP runs is part of the image. With IPP off, OpenCV's own kernels give the same bytes with AVX2 as
with AVX-512 (``OPENCV_CPU_DISABLE``; ``tests/test_simulator_basics.py``); below AVX2, ``cv2.remap`` and ``cv2.blur``
change about one image in 750 (docs/studies/openblas-kernels.md).

OpenCV keeps IPP's switch per thread (``cv::ipp::setUseIPP`` writes thread-local data; a new thread starts with IPP
on), so :func:`ipp_off` is called by the code that renders or resizes, in its own thread, not once at import.

Used by the embedded renderer (``generate``, ``evaluate``'s PPCs, ``task2``, ``pidc render``) and by the backbones'
size conversion (every stage but ``generate``, and the ``pidc`` CLI).
"""

from __future__ import annotations

import cv2

__all__ = ["ipp_off"]


def ipp_off() -> None:
    """Turn Intel's IPP off for OpenCV calls in the calling thread (a thread-local flag: cheap enough per call)."""
    cv2.ipp.setUseIPP(False)
