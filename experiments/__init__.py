"""What a researcher runs: the RE10K / DL3DV / Kubric entry points and the paper's studies.

Modules: `config` (typed settings and presets), `data` (synthetic set, batches, held-out scenes),
`weights`, `training`, `tasks` (the commands and the per-dataset `Task`), `results` (the results
folder), `pictures` (readable grids), `dynamic_pictures` (Kubric's dynamic pictures and scene-flow
scores), `pretrained/` (shipped weights), `cli` (tyro). Scoring is `tokengs_jax.evaluation`.

    python -m experiments.re10k                  # synthetic default: generate, evaluate the shipped weights
    python -m experiments.re10k eval paper --data-dir /data/re10k \\
        --official-checkpoint tokengs_re10k.safetensors
    python -m experiments.studies.camera_noise
"""
