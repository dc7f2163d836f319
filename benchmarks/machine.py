"""What every benchmark records about the machine it ran on (imported by the benchmark scripts)."""

from __future__ import annotations

import os
import platform
import sys
from pathlib import Path


def machine_info(**extra: object) -> dict:
    """CPU model and count, 1-min load, Python, platform, and the versions of numeric libraries already imported."""
    cpu = platform.processor()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    info: dict = {
        "cpu": cpu,
        "cpu_count": os.cpu_count(),
        "load_avg_1min": os.getloadavg()[0] if hasattr(os, "getloadavg") else None,
        "python": platform.python_version(),
        "platform": platform.platform(),
    }
    for name in ("numpy", "torch", "onnxruntime", "cv2"):
        if name in sys.modules:
            info[name] = getattr(sys.modules[name], "__version__", "?")
    info.update(extra)
    return info
