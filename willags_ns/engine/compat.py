"""Small compatibility shims between nerfstudio 1.1.5 and current torch. Each says why it exists."""

import sys

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


def quick_external_method_check() -> None:
    """Make nerfstudio's list of installable external methods cheap to build.

    Why: importing nerfstudio 1.1.5's method registry builds one `ExternalMethodDummyTrainerConfig` per installable
    method (26 of them), and each one's `__post_init__` calls `inspect.stack()` only to see whether
    `get_external_methods` is the caller. `inspect.stack()` reads the source of every frame on the stack and scans
    `sys.modules` for each one; with torch imported that is several seconds of every `ns-train`, `ns-eval`,
    `ns-render` and `ns-viewer` start, and again in every process of a multi-GPU run (each one imports the registry).
    The same test on the caller's code name (`sys._getframe`) replaces it; a dummy built anywhere else (the user asked
    `ns-train` for an external method that is not installed) goes through nerfstudio's own `__post_init__` unchanged:
    its install offer. Applied when willags' method configs are loaded, which nerfstudio does before it builds the
    list."""
    try:
        from nerfstudio.configs import external_methods
    except ImportError:  # another nerfstudio layout: nothing to speed up
        return
    cls = getattr(external_methods, "ExternalMethodDummyTrainerConfig", None)
    original = getattr(cls, "__post_init__", None)
    if cls is None or original is None or getattr(original, "quick_caller_check", False):
        return

    def __post_init__(self) -> None:
        # frame 0: here; 1: the dataclass __init__; 2: whoever built the dummy
        if sys._getframe(2).f_code.co_name == "get_external_methods":
            return
        original(self)

    __post_init__.quick_caller_check = True  # type: ignore[attr-defined]
    cls.__post_init__ = __post_init__


CONFIG_YML_CLASSES: dict[str, str] = {
    "willags_ns.trainer.WillagsTrainerConfig": "willags_ns.engine.trainer.WillagsTrainerConfig",
    "willags_ns.trainer.WillagsTrainer": "willags_ns.engine.trainer.WillagsTrainer",
    "willags_ns.pipeline.WillagsPipelineConfig": "willags_ns.engine.pipeline.WillagsPipelineConfig",
    "willags_ns.pipeline.WillagsPipeline": "willags_ns.engine.pipeline.WillagsPipeline",
    "willags_ns.distributed.DataParallelConfig": "willags_ns.engine.distributed.DataParallelConfig",
    "willags_ns.teacher.TeacherConfig": "willags_ns.mask.teacher.TeacherConfig",
    "willags_ns.transient.MaskConfig": "willags_ns.mask.rule.MaskConfig",
    "willags_ns.transient.PerceptualMaskConfig": "willags_ns.mask.rule.MaskConfig",
    "willags_ns.mask.transient.MaskConfig": "willags_ns.mask.rule.MaskConfig",
    "willags_ns.mask_health.MaskHealthConfig": "willags_ns.mask.health.MaskHealthConfig",
    "willags_ns.static_support.StaticSupportConfig": "willags_ns.mask.static_support.StaticSupportConfig",
    "willags_ns.model.WillagsModelConfig": "willags_ns.config.WillagsModelConfig",
}
"""The classes a config.yml names by the module that held them when it was written (its YAML tags
`!!python/object:M.C` and `!!python/name:M.C`), and where each class is: runs trained before the package had its
rooms load, evaluate and render. PerceptualMaskConfig is the mask's settings under the flat layout's name."""


def register_config_yml_classes(loader: type) -> None:
    """Teach YAML `loader` (nerfstudio's ns-eval, ns-render, ns-viewer and `--load-config` read config.yml with
    yaml.Loader) the CONFIG_YML_CLASSES: an exact tag takes precedence over PyYAML's import of the named module. The
    package's import registers them; nerfstudio imports the package (its method configs) before it reads a file."""
    for old, new in CONFIG_YML_CLASSES.items():

        def construct_object(ldr, node, new=new):
            return ldr.construct_python_object(new, node)

        def construct_name(ldr, node, new=new):
            return ldr.construct_python_name(new, node)

        loader.add_constructor(f"tag:yaml.org,2002:python/object:{old}", construct_object)
        loader.add_constructor(f"tag:yaml.org,2002:python/name:{old}", construct_name)


LIBRARY_NOISE = (
    (FutureWarning, r"`torch\.cuda\.amp\.(GradScaler|custom_fwd|custom_bwd)\(args\.\.\.\)` is deprecated"),
    (UserWarning, r"Converting a tensor with requires_grad=True to a scalar"),
    (UserWarning, r"To copy construct from a tensor, it is recommended to use sourceTensor\.detach\(\)\.clone\(\)"),
)
"""(category, message pattern) of warnings nerfstudio 1.1.5's own calls raise under current torch on every run: the
deprecated torch.cuda.amp spellings in its trainer and field components, its tensorboard writer's float() of a
loss, and the torch.tensor() of a tensor in its interpolated camera path (`willags-render interpolate`). Nothing a
user can change; hidden from the terminal."""


def silence_library_noise() -> None:
    """Ignore the warnings of LIBRARY_NOISE (only those messages; every other warning still shows)."""
    import warnings

    for category, pattern in LIBRARY_NOISE:
        warnings.filterwarnings("ignore", message=pattern, category=category)


def one_line_own_warnings() -> None:
    """Python prints a warning as ``file:line: Category: message`` plus the source line; willags' own warnings (their
    message starts with ``willags:``) print as the message alone, one line. Others are left as they are."""
    import warnings

    if getattr(warnings.formatwarning, "willags", False):
        return
    previous = warnings.formatwarning

    def formatwarning(message, category, filename, lineno, line=None):
        if str(message).startswith("willags:"):
            return f"{message}\n"
        return previous(message, category, filename, lineno, line)

    formatwarning.willags = True  # type: ignore[attr-defined]
    warnings.formatwarning = formatwarning
