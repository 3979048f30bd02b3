"""The appearance panel of nerfstudio's viewer (`ns-viewer` and during training).

Every control writes an appearance SPEC (willags_ns.appearance_spec, the same parser as `willags-render
--appearance`), shown and editable in "Appearance spec"; the SPEC's latent becomes `model.render_latent`. The model
caches the colour field per latent, so moving the camera afterwards costs only the rasteriser.

Controls (in panel order; nerfstudio lists a module's viewer elements sorted by attribute name, hence the
numbered attribute names):

- Appearance A / Appearance B: the mean, a photo (path field), a random sample (seed), or any training image;
- Search training images: filters both lists (all training images, not only the frustums drawn);
- A -> B: the interpolation weight (0 shows A);
- Photo path + Use photo: a new photo's appearance through the VAE encoder;
- Random seed + Random appearance: z ~ N(0, I), the button draws the next seed;
- Show transient mask / teacher: for appearance A's training view, the training image, the EMA teacher's render
  and the transient mask the model computes for it (as training does), shown as a picture in the panel;
- Latent norm and a status line (errors of a bad SPEC name the bad part; the previous appearance stays).
"""

import base64
import io
import os
import threading
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import nn

from willags_ns.appearance_spec import (
    AppearanceSpecError,
    ImageSpec,
    RefineOptions,
    image_index,
    interpolate_latents,
    parse_spec,
    resolve_latent,
    sample_latent,
)

if TYPE_CHECKING:
    from willags_ns.model import WillagsModel

__all__ = [
    "AppearanceControls",
    "appearance_controls",
    "guard_viewer_host",
    "interpolate_latents",
    "sample_latent",
    "spec_from_choices",
]

VIEWER_HOST_ENV = "WILLAGS_VIEWER_HOST"
"""Host the viewer of a willags checkpoint listens on under `ns-viewer` (default 127.0.0.1; 0.0.0.0 exposes it)."""


def guard_viewer_host() -> None:
    """`ns-viewer` replaces the host saved in a run's config with its own default, 0.0.0.0: anyone on the network
    could drive the viewer. Installed when a willags pipeline loads for viewing (test mode), so only willags
    checkpoints are affected: the viewer then listens on 127.0.0.1, unless $WILLAGS_VIEWER_HOST names a host
    (WILLAGS_VIEWER_HOST=0.0.0.0 exposes it) or --viewer.websocket-host names one other than 0.0.0.0."""
    from nerfstudio.utils.rich_utils import CONSOLE
    from nerfstudio.viewer import viewer as ns_viewer

    original = ns_viewer.Viewer.__init__
    if getattr(original, "_willags_host_guard", False):
        return

    def __init__(self, config, *args, **kwargs):
        host = os.environ.get(VIEWER_HOST_ENV)
        if host:
            config.websocket_host = host
        elif config.websocket_host == "0.0.0.0":
            config.websocket_host = "127.0.0.1"
            CONSOLE.log(
                f"willags: the viewer listens on 127.0.0.1 only; {VIEWER_HOST_ENV}=0.0.0.0 opens it to the network"
            )
        original(self, config, *args, **kwargs)

    __init__._willags_host_guard = True  # type: ignore[attr-defined]
    ns_viewer.Viewer.__init__ = __init__  # type: ignore[method-assign]


MEAN = "mean of training images"
PHOTO = "photo (path below)"
SAMPLE = "random sample (seed below)"
SPECIAL = (MEAN, PHOTO, SAMPLE)
MAX_LISTED = 500
"""At most this many training images are listed at once (the search field narrows a longer list)."""


def spec_from_choices(a: str, b: str, t: float, photo: str, seed: int) -> str:
    """The SPEC of the panel's state: entry A, entry B (SPECIAL entries or training image names), weight t."""

    def one(entry: str) -> str:
        if entry == MEAN:
            return "mean"
        if entry == PHOTO:
            return f"photo:{photo.strip()}"
        if entry == SAMPLE:
            return f"sample:{int(seed)}"
        return f"image:{entry}"

    t = float(t)
    if t <= 0.0 or a == b:
        return one(a)
    if t >= 1.0:
        return one(b)
    return f"interp:{one(a)},{one(b)},{t:.3g}"


def filter_names(names: list[str], query: str, limit: int = MAX_LISTED) -> list[str]:
    """Training image names containing `query` (case-insensitive), at most `limit`."""
    q = query.strip().lower()
    return [n for n in names if q in n.lower()][:limit]


def _png_data_url(img: np.ndarray) -> str:
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(img).save(buf, format="PNG")
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode()


@torch.no_grad()
def training_view_panels(model: "WillagsModel", train_dataset, idx: int, max_width: int = 320) -> np.ndarray:
    """[training image | teacher render | transient mask] of training image `idx` as one uint8 picture.

    The mask is computed as training computes it at the model's current step (teacher latent from the image, the
    comparison of mask.distance with the teacher render (VGG features or colour residual), its threshold and the
    rejection of mostly-flagged images).
    """
    from willags_ns.eval.mask_eval import expected_render, teacher_render, training_view
    from willags_ns.mask.rule import compare_to_teacher

    cam, image, _ = training_view(train_dataset, idx)
    gt = torch.from_numpy(image).float().div(255.0).to(model.device)
    teacher = teacher_render(model, cam, gt, idx)
    cfg = model.config
    if model.perceptual is not None:  # the comparison of mask.distance; a rejected mask is all False
        expected = expected_render(model, cam, idx)  # the scene's expected residual, when it has one
        transient, _, _ = compare_to_teacher(cfg.mask, model.step, gt, teacher, model.perceptual, expected=expected)
    else:  # mask.enabled False: no mask, every pixel is supervised
        transient = torch.zeros(gt.shape[:2], dtype=torch.bool, device=gt.device)
    overlay = gt.clone()
    overlay[transient] = 0.5 * overlay[transient] + 0.5 * torch.tensor([1.0, 0.0, 0.0], device=gt.device)
    strip = torch.cat([gt, teacher, overlay], dim=1).clamp(0, 1)
    out = (strip.cpu().numpy() * 255).round().astype(np.uint8)
    if out.shape[1] > max_width:
        from PIL import Image

        h = max(1, round(out.shape[0] * max_width / out.shape[1]))
        out = np.asarray(Image.fromarray(out).resize((max_width, h), Image.Resampling.LANCZOS))
    return out


def _markdown_element(name: str, content: str):
    """A markdown ViewerElement (nerfstudio has none): status lines and the mask / teacher picture."""
    from nerfstudio.viewer.viewer_elements import ViewerElement

    class ViewerMarkdown(ViewerElement[str]):
        def __init__(self, name: str, content: str):
            super().__init__(name)
            self.content = content

        def _create_gui_handle(self, viser_server) -> None:
            from pathlib import Path

            # image_root only silences viser's warning: our pictures are inline data URLs
            self.gui_handle = viser_server.gui.add_markdown(self.content, image_root=Path.cwd())  # type: ignore

        def install(self, viser_server) -> None:
            self._create_gui_handle(viser_server)

        def set_content(self, content: str) -> None:
            self.content = content
            if self.gui_handle is not None:
                self.gui_handle.content = content  # type: ignore[union-attr]

    return ViewerMarkdown(name, content)


VIEWER_PHOTO_REFINE_STEPS = 50
"""Adam steps fitting a photo's latent in the viewer when the model has no encoder (`photo:P --refine-steps 50`)."""


class AppearanceControls(nn.Module):
    """Holds the viewer elements (nerfstudio finds ViewerElements on nn.Modules under the pipeline).

    An nn.Module without parameters so the viewer's tree walk reaches it; the model is kept in `_model` (a plain
    attribute, not a submodule, to avoid a reference cycle in the module tree).
    """

    _model: "WillagsModel"

    def __init__(self, model: "WillagsModel", image_names: list[str] | None = None):
        super().__init__()
        object.__setattr__(self, "_model", model)
        self._train_dataset = None
        self._lock = threading.RLock()  # viser runs each callback in its own thread
        self._photo_cache: dict = {}
        self.spec = "mean"
        """The SPEC now rendered."""
        self.set_image_names(image_names or list(model.image_names))
        # while the viewer shows this panel, its choice (the mean included) is what the model renders: a camera's
        # cam_idx (the viewer's cameras carry one) does not pick a training image's appearance
        model.latents.panel = self

    def is_open(self) -> bool:
        """Whether the viewer shows the panel (its elements got their GUI handles)."""
        return getattr(self.p01_a, "gui_handle", None) is not None

    def set_train_dataset(self, dataset) -> None:
        """The training dataset (images and cameras) for the transient mask / teacher view."""
        self._train_dataset = dataset

    def set_image_names(self, names: list[str]) -> None:
        from nerfstudio.viewer.viewer_elements import (
            ViewerButton,
            ViewerCheckbox,
            ViewerDropdown,
            ViewerNumber,
            ViewerSlider,
            ViewerText,
        )

        self._names = list(names)
        opts = list(SPECIAL) + filter_names(self._names, "")
        ctl = lambda _: self._on_controls()  # noqa: E731
        self.p01_a = ViewerDropdown("Appearance A", MEAN, opts, cb_hook=ctl, hint="shown at A -> B = 0")
        self.p02_b = ViewerDropdown("Appearance B", opts[-1], opts, cb_hook=ctl, hint="shown at A -> B = 1")
        self.p03_search = ViewerText(
            "Search training images", "", cb_hook=lambda _: self._on_search(), hint="filters both lists"
        )
        self.p04_t = ViewerSlider("A -> B", 0.0, 0.0, 1.0, 0.01, cb_hook=ctl, hint="interpolation weight")
        self.p05_photo = ViewerText(
            "Photo path", "", hint="any photo: its appearance fitted to it (or through the VAE encoder)"
        )
        self.p06_use_photo = ViewerButton("Use photo", cb_hook=lambda _: self._choose(PHOTO))
        self.p07_seed = ViewerNumber(
            "Random seed", 0, cb_hook=ctl, hint="a new appearance drawn from this seed (sample:SEED)"
        )
        self.p08_random = ViewerButton("Random appearance", cb_hook=lambda _: self._next_sample())
        self.p09_spec = ViewerText(
            "Appearance spec", "mean", cb_hook=lambda _: self._on_spec_text(), hint="willags-render --appearance"
        )
        # text, not a number field: viser rounds a number field to the step it infers from the initial value
        self.p10_norm = ViewerText("Latent norm", "", disabled=True, hint="|z| of the rendered appearance")
        self.p11_status = _markdown_element("status", "")
        self.p12_show_mask = ViewerCheckbox(
            "Show transient mask / teacher",
            False,
            cb_hook=lambda _: self._update_training_view(),
            hint="the chosen training image: image | teacher render | transient mask (red)",
        )
        self.p13_training_view = _markdown_element("training view", "")

    # ------------------------------------------------------------------ callbacks
    def _on_search(self) -> None:
        opts = list(SPECIAL) + filter_names(self._names, str(self.p03_search.value))
        for dd in (self.p01_a, self.p02_b):
            keep = dd.value
            dd.set_options(opts if keep in opts else opts + [keep])  # the chosen entry stays selectable

    def _choose(self, entry: str) -> None:
        """Show `entry` as appearance A (buttons)."""
        with self._lock:
            if entry not in self.p01_a.options:
                self.p01_a.set_options(self.p01_a.options + [entry])
            self.p01_a.value = entry
            self.p04_t.value = 0.0
            self._on_controls()

    def _next_sample(self) -> None:
        with self._lock:
            self.p07_seed.value = int(self.p07_seed.value) + 1
            self._choose(SAMPLE)

    def _on_controls(self) -> None:
        spec = spec_from_choices(
            self.p01_a.value, self.p02_b.value, self.p04_t.value, str(self.p05_photo.value), int(self.p07_seed.value)
        )
        self.apply_spec(spec)

    def _on_spec_text(self) -> None:
        text = str(self.p09_spec.value).strip()
        if text and text != self.spec:
            self.apply_spec(text)

    # ------------------------------------------------------------------ the one place the latent is set
    def apply_spec(self, spec: str) -> bool:
        """Render `spec` from now on; on a bad SPEC keep the current appearance and show the error. True if applied."""
        m = self._model
        with self._lock:
            try:
                parsed = parse_spec(spec, "viewer")
                refine, cams = None, None
                if m.appearance_nets.vae is None and self._train_dataset is not None:
                    # no encoder (an embedding-table model, the default): a photo's latent is fitted to it
                    refine, cams = RefineOptions(steps=VIEWER_PHOTO_REFINE_STEPS), self._train_dataset.cameras
                z = resolve_latent(parsed, m, refine=refine, cameras=cams, cache=self._photo_cache, context="viewer")
            except AppearanceSpecError as e:
                self.p11_status.set_content(f"**{e}**")
                return False
            # the mean stays the model's default (None): it follows training as latents are refreshed
            m.render_latent = None if spec.strip() == "mean" else z
            self.spec = spec
            self.p09_spec.value = spec
            self.p10_norm.value = f"{float(z.norm()):.4f}"
            self.p11_status.set_content("")
            self._update_training_view()
        return True

    def _update_training_view(self) -> None:
        panel = self.p13_training_view
        if not bool(self.p12_show_mask.value):
            panel.set_content("")
            return
        try:  # the training image shown: the SPEC's (typed or chosen), else appearance A if it is one
            parsed = parse_spec(self.spec)
        except AppearanceSpecError:
            parsed = None
        a = parsed.key if isinstance(parsed, ImageSpec) else self.p01_a.value
        if a in SPECIAL:
            panel.set_content("choose a training image as the appearance to see its transient mask")
            return
        if self._train_dataset is None:
            panel.set_content("no training dataset loaded")
            return
        m = self._model
        try:
            idx = image_index(a, self._names)
            was_training = m.training
            m.eval()
            img = training_view_panels(m, self._train_dataset, idx)
            m.train(was_training)
        except Exception as e:  # the viewer must survive a failing diagnostic
            panel.set_content(f"**training view unavailable: {e}**")
            return
        name = self._names[idx]
        panel.set_content(f"{name}: image | teacher | transient mask (red)\n\n![training view]({_png_data_url(img)})")


def appearance_controls(model: "WillagsModel") -> AppearanceControls:
    """The panel of `model` (made on first call, with the model's training image names): what the pipeline
    attaches as `pipeline.viewer_controls`, where nerfstudio's viewer finds its elements."""
    panel = model.latents.panel
    return panel if isinstance(panel, AppearanceControls) else AppearanceControls(model)
