"""The engine around nerfstudio: trainer, pipeline, several GPUs, checkpoints, time budget, input checks, progress,
step profile and the shims between nerfstudio and current torch."""
