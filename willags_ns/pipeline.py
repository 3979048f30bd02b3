"""WillagsPipeline: nerfstudio's VanillaPipeline, plus handing the training image to the model.

Why a pipeline at all: the beta-VAE encodes the *training image itself* into the appearance latent before the
scene is rendered, but nerfstudio calls `model(camera)` without the batch. The pipeline gives the model the
batch first (`model.set_train_batch`), then runs the usual forward / metrics / loss sequence unchanged.
"""

from dataclasses import dataclass, field
from pathlib import Path

from nerfstudio.pipelines.base_pipeline import VanillaPipeline, VanillaPipelineConfig

from willags_ns.eval.protocol import EvalProtocolConfig, eval_split_images, evaluate_model


@dataclass
class WillagsPipelineConfig(VanillaPipelineConfig):
    """VanillaPipeline that passes the training batch to the model before its forward pass."""

    _target: type = field(default_factory=lambda: WillagsPipeline)
    eval_protocol: EvalProtocolConfig = field(default_factory=EvalProtocolConfig)
    """NeRF-W protocol used by `ns-eval` (fit the latent on the left half of each test image, score the right)."""


class WillagsPipeline(VanillaPipeline):
    config: WillagsPipelineConfig

    def __init__(self, config: WillagsPipelineConfig, *args, **kwargs):
        super().__init__(config, *args, **kwargs)
        names = [Path(p).name for p in self.datamanager.train_dataparser_outputs.image_filenames]
        if hasattr(self.model, "set_train_image_names"):
            self.model.set_train_image_names(names)
        controls = getattr(self.model, "viewer_controls", None)
        if controls is not None:  # the viewer panel shows a training view's transient mask / teacher render
            controls.set_train_dataset(self.datamanager.train_dataset)

    def get_train_loss_dict(self, step: int):
        camera, batch = self.datamanager.next_train(step)
        self.model.set_train_batch(batch)  # type: ignore[attr-defined]
        model_outputs = self._model(camera)
        metrics_dict = self.model.get_metrics_dict(model_outputs, batch)
        loss_dict = self.model.get_loss_dict(model_outputs, batch, metrics_dict)
        return model_outputs, loss_dict, metrics_dict

    def get_average_eval_image_metrics(self, step=None, output_path=None, get_std: bool = False):
        """`ns-eval`: the NeRF-W protocol over the eval split (see willags_ns/eval/protocol.py).

        Headline `psnr`/`ssim`/`lpips` are right-half scores with the fitted latent; `encoder_*` use the encoder's
        latent without optimisation; `full_*` score the whole image.
        """
        ds = self.datamanager.eval_dataset
        images = eval_split_images(self.datamanager)
        names = [Path(p).name for p in ds.image_filenames]
        self.eval()
        agg, per_image = evaluate_model(self.model, ds.cameras, images, self.config.eval_protocol, names)
        self.train()
        if get_std and len(per_image) > 1:
            import statistics

            for k in ("psnr", "ssim", "lpips"):
                if k in per_image[0]:
                    agg[f"{k}_std"] = statistics.pstdev(float(r[k]) for r in per_image)
        return agg
