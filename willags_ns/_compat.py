"""Small compatibility shims between nerfstudio 1.1.5 and current torch. Each says why it exists."""

import numpy as np
import torch


def register_checkpoint_safe_globals() -> None:
    """Let nerfstudio's own `torch.load(path)` calls read checkpoints under torch>=2.6's `weights_only=True`.

    Why: nerfstudio 1.1.5 saves optimizer/scheduler/grad-scaler state that contains numpy scalars and dtypes;
    torch>=2.6 refuses to unpickle those by default, so ns-viewer, ns-render, ns-eval and `--load-dir` fail.
    Allow-listing exactly these numpy types (not disabling weights_only) keeps loading safe.
    """
    add = getattr(torch.serialization, "add_safe_globals", None)
    if add is None:  # torch < 2.4 loads everything anyway
        return
    safe: list = [np.dtype, np.ndarray]
    try:  # numpy 2 renamed np.core -> np._core
        from numpy._core import multiarray
    except ImportError:
        from numpy.core import multiarray
    safe.extend([multiarray.scalar, multiarray._reconstruct])
    dtypes = getattr(np, "dtypes", None)
    if dtypes is not None:  # numpy >= 1.25 pickles dtypes as np.dtypes.<X>DType classes
        safe.extend(getattr(dtypes, n) for n in dir(dtypes) if n.endswith("DType"))
    add(safe)
