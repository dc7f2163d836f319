"""pidc's library: physically interpretable, probabilistic domain characterization.

Pure Python over numpy/torch/zuko/cvxpy/onnxruntime. It imports no Prefect, DVC or MLflow.

Imported by every stage and the ``pidc`` CLI.
"""

__version__ = "0.1.0"
