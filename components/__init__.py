"""pidc's library: physically interpretable, probabilistic domain characterization.

Pure Python over numpy/torch/zuko/cvxpy/onnxruntime. It imports no Prefect, DVC or MLflow.

Importing it first (every stage and the ``pidc`` CLI do) pins numpy's run-time SIMD dispatch to the baseline
kernels, unless the user set ``NPY_DISABLE_CPU_FEATURES``: numpy chooses AVX2 or AVX-512 kernels by CPU and rounds
float32 ``exp`` differently in each, so one weather and scene rendered to images that differed from one CPU to
another (measured: AVX2 against the x86-64-v2 baseline changed 5 of 40 images, a few pixels each by one level;
docs/reproducibility.md). With the baseline kernels everywhere the rendered data are byte-identical across x86-64
machines, at the same render speed (116 against 119 images/s on one core). It has no effect once numpy is imported.

Imported by every stage and the ``pidc`` CLI.
"""

import os

#: numpy's dispatched CPU feature groups above the x86-64-v2 baseline (names unknown to a CPU are ignored)
NUMPY_DISPATCH_OFF = "X86_V3,X86_V4,AVX512_ICL,AVX512_SPR"
os.environ.setdefault("NPY_DISABLE_CPU_FEATURES", NUMPY_DISPATCH_OFF)


def numpy_kernels() -> str:
    """The kernels numpy runs in this process for float32 ``exp``: ``"baseline"`` once pinned, else the dispatched
    target (e.g. ``"AVX512_SKX"``: numpy was imported before ``components``, or with another
    ``NPY_DISABLE_CPU_FEATURES``)."""
    import numpy as np

    info = np.lib.introspect.opt_func_info(func_name="exp", signature="float32")["exp"]
    return str(next(iter(info.values()))["current"])


__version__ = "0.1.0"
