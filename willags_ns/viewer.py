"""Appearance controls for the nerfstudio viewer: pick any training image's appearance, interpolate two,
or sample a new one (z ~ N(0, I)).

The controls only set `model.render_latent`; rendering recomputes the tri-plane features once per latent change
(the model caches f_d), so moving the camera costs only the view-dependent decoder and the rasteriser.
"""

from typing import TYPE_CHECKING

import torch
from torch import Tensor, nn

if TYPE_CHECKING:
    from willags_ns.model import WillagsModel

MODES = ("mean of training images", "training image", "interpolate A -> B", "random sample")


def interpolate_latents(z_a: Tensor, z_b: Tensor, t: float) -> Tensor:
    """Linear interpolation between two latents; t=0 gives z_a, t=1 gives z_b."""
    return (1.0 - t) * z_a + t * z_b


def sample_latent(dim: int, seed: int, device: "torch.device | str" = "cpu") -> Tensor:
    """A new appearance: z ~ N(0, I), reproducible from the seed."""
    g = torch.Generator().manual_seed(int(seed))
    return torch.randn(dim, generator=g).to(device)


class AppearanceControls(nn.Module):
    """Holds the viewer elements (nerfstudio finds ViewerElements on nn.Modules under the pipeline).

    An nn.Module without parameters so the viewer's tree walk reaches it; the model is kept in `_model` (a plain
    attribute, not a submodule, to avoid a reference cycle in the module tree).
    """

    _model: "WillagsModel"

    def __init__(self, model: "WillagsModel", image_names: list[str] | None = None):
        super().__init__()
        object.__setattr__(self, "_model", model)
        self.set_image_names(image_names or [f"image {i}" for i in range(max(model.num_train_data, 1))])

    def set_image_names(self, names: list[str]) -> None:
        from nerfstudio.viewer.viewer_elements import (
            ViewerButton,
            ViewerDropdown,
            ViewerNumber,
            ViewerSlider,
        )

        self._names = list(names)
        opts = self._names
        self.mode = ViewerDropdown("Appearance", MODES[0], list(MODES), cb_hook=lambda _: self.apply())
        self.image_a = ViewerDropdown("Appearance image A", opts[0], opts, cb_hook=lambda _: self.apply())
        self.image_b = ViewerDropdown("Appearance image B", opts[-1], opts, cb_hook=lambda _: self.apply())
        self.t = ViewerSlider("Interpolation t", 0.5, 0.0, 1.0, 0.01, cb_hook=lambda _: self.apply())
        self.seed = ViewerNumber("Sample seed", 0, cb_hook=lambda _: self.apply())
        self.resample = ViewerButton("New random appearance", cb_hook=lambda _: self._next_seed())

    def _next_seed(self) -> None:
        self.seed.value = int(self.seed.value) + 1
        self.mode.value = MODES[3]
        self.apply()

    def latent_for(self, mode: str, a: str, b: str, t: float, seed: int) -> Tensor | None:
        """The latent the controls describe (None = the model's default, the mean training latent)."""
        m = self._model
        names = self._names
        if mode == MODES[1]:
            return m.train_latents[names.index(a)].clone()
        if mode == MODES[2]:
            return interpolate_latents(m.train_latents[names.index(a)], m.train_latents[names.index(b)], float(t))
        if mode == MODES[3]:
            return sample_latent(int(m.train_latents.shape[1]), seed, m.device)
        return None

    def apply(self) -> None:
        self._model.render_latent = self.latent_for(
            self.mode.value, self.image_a.value, self.image_b.value, self.t.value, int(self.seed.value)
        )


APPEARANCE_ENV = "WILLAGS_APPEARANCE"
"""Environment variable read by the model when no appearance was chosen in code: lets nerfstudio's own
`ns-render`, `ns-export gaussian-splat` and `ns-viewer` use a chosen appearance (they take no model options)."""


def latent_from_spec(spec: str, image_names: list[str], train_latents: Tensor, seen: Tensor) -> Tensor | None:
    """Parse an appearance spec into a latent ([D]) or None for the default (mean of training latents).

    Specs: ``mean`` | ``image:NAME_OR_INDEX`` | ``sample:SEED`` | ``interp:A,B,T`` (A, B names or indices).
    Raises ValueError naming the bad part.
    """

    def index_of(key: str) -> int:
        key = key.strip()
        if key in image_names:
            i = image_names.index(key)
        elif key.isdigit() and int(key) < len(image_names):
            i = int(key)
        else:
            stems = [n.rsplit(".", 1)[0] for n in image_names]
            if key not in stems:
                raise ValueError(
                    f"{APPEARANCE_ENV}: unknown training image {key!r}; known: {', '.join(image_names[:8])}"
                    + (" ..." if len(image_names) > 8 else "")
                )
            i = stems.index(key)
        if not bool(seen[i]):
            raise ValueError(f"{APPEARANCE_ENV}: training image {image_names[i]!r} was never encoded during training")
        return i

    spec = spec.strip()
    kind, _, arg = spec.partition(":")
    if kind in ("", "mean"):
        return None
    if kind == "image":
        return train_latents[index_of(arg)].clone()
    if kind == "sample":
        try:
            seed = int(arg or 0)
        except ValueError:
            raise ValueError(f"{APPEARANCE_ENV}: sample seed must be an integer, got {arg!r}") from None
        return sample_latent(int(train_latents.shape[1]), seed, train_latents.device)
    if kind == "interp":
        parts = arg.split(",")
        if len(parts) != 3:
            raise ValueError(f"{APPEARANCE_ENV}: interp needs 'interp:A,B,T', got {spec!r}")
        try:
            t = float(parts[2])
        except ValueError:
            raise ValueError(f"{APPEARANCE_ENV}: interpolation T must be a number, got {parts[2]!r}") from None
        return interpolate_latents(train_latents[index_of(parts[0])], train_latents[index_of(parts[1])], t)
    raise ValueError(
        f"{APPEARANCE_ENV}: unknown appearance spec {spec!r} (mean | image:NAME | sample:SEED | interp:A,B,T)"
    )
