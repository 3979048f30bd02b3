"""Tools around the method (willags_ns's core: the model, its rooms and the methods): what reads a scene or photos
to decide or prepare a run, without being part of what trains.

- `inspection.py`: willags-inspect's implementation (the command line: scripts/inspect.py), the evidence a scene
  gives (appearance change, transients, open background) and the recommended switches;
- `autoconfig.py`: applies that recommendation to a model config before the model is built (`auto_config`);
- `sfm.py`: willags-process's implementation (the command line: scripts/process.py), photos to a COLMAP scene with
  pycolmap;
- `progress.py`: the progress lines of long commands (ns-eval, willags-render, willags-export, willags-process).

The time budget (willags_ns/engine/time_budget.py) is a tool too; it stays beside the trainer that applies it.
"""
