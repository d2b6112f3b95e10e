"""What a researcher runs: the RE10K / DL3DV / Kubric entry points and the paper's studies.

Laid out by role (`docs/design.md` has a line per module):
- entry points, thin (presets + `main`, their docstring the `--help`): `re10k`, `dl3dv`,
  `kubric`; `studies/` (one script per study); `view` (the browser viewer, `viewer/`);
  `launch` (N local processes of one job); `weights` (`ship`: weights into `pretrained/`).
- what the entry points share: `cli` (tyro), `config` (typed settings and presets), `data`
  (synthetic sets, batches, held-out scenes), `tasks` (the commands and the static datasets'
  `Task`), `training` (the library loop with a progress bar and TensorBoard), `results` (the
  results folder), `weights` (params on disk, a command's starting weights).
- per dataset: `kubric_task` (Kubric's settings and `Task`), `kubric_data` (its synthetic subsets,
  scene sources, example configuration and view selection).
- figures: `figures` (picture grids and charts, PIL), `dynamic_pictures` (Kubric's dynamic
  pictures and scene-flow scores), `dynamic_videos` (Kubric's videos, as the official
  `render_kubric_dyn.py`'s).
- baselines: `pixel_baseline` (the pixel-aligned model); the copy baselines and every score are
  `tokengs_jax.evaluation`'s.
- data: `pretrained/` (the shipped weights, with provenance).

    python -m experiments.re10k                  # synthetic default: generate, evaluate the shipped weights
    python -m experiments.re10k eval paper --data-dir /data/re10k \\
        --official-checkpoint tokengs_re10k.safetensors
    python -m experiments.studies.camera_noise
"""
