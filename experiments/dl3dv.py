"""DL3DV: 2/4/6-view train / finetune / eval; with no arguments, a synthetic 4-view run.

    python -m experiments.dl3dv                                   # = run synthetic-4view
    python -m experiments.dl3dv eval paper-6view --data-dir /data/dl3dv \\
        --eval-index assets/dl3dv_start_0_distance_50_ctx_6v_tgt_8v.json \\
        --official-checkpoint tokengs_dl3dv_6view.safetensors
    python -m experiments.dl3dv finetune paper-2view --data-dir /data/dl3dv_zips \\
        --eval-index dl3dv_start_0_distance_50_ctx_2v_tgt_4v.json --official-checkpoint w.safetensors

Data (`--data-dir D`, the format told from what D holds; a folder of neither is refused):
- pixelSplat chunks: `D/train`, `D/test` (`*.torch` + `index.json`), as `experiments.re10k`.
- DL3DV as it ships (the official training's input): scene zips `<scene>.zip` holding
  `<scene>/transforms.json` + `<scene>/images_4/` (or the same unpacked, benchmark zips with
  `gaussian_splat/`, subset folders `1K/` ... `11K/`). Either `D/train` and `D/test` (e.g. links
  to DL3DV-ALL-960P and DL3DV-10K-Benchmark: a scene in both is never trained on), or one folder
  of scenes whose held-out ones `--eval-index` names (DepthSplat key -> {context, target} JSON or
  the Long-LRM list; needed to evaluate): those are scored and never trained on.
  `tokengs_jax.data.dl3dv` reads them. The synthetic presets need `--dataset dl3dv` there (DL3DV's
  sampler and translation scale).

Presets:
- `synthetic-{2,4,6}view`: the synthetic RE10K-format rooms (shared with `experiments.re10k`),
  the `tiny` model, N input views over a 16-frame span (context extension of the same training
  recipe); results in `outputs/dl3dv/synthetic_<N>view`.
- `paper-{2,4,6}view`: the official DL3DV presets (`dl3dv_<N>view`: 3 / 12 layers, 4096 tokens,
  256x448), DL3DV sampler (gap 10-40, 4 targets) and translation scale 0.15; finetuning recipe of
  the paper (10k steps, lr 4e-5, 400 warm-up). Eval JSONs: pass the benchmark's index with
  `--eval-index` (the key -> {context, target} format; see docs/experiments.md for the list format).
  Loss: the official default (MSE + 0.2 SSIM), as the official `finetune_dl3dv_<N>view`.
- `paper-base`: the official base training (`train_dl3dv_base`), run with `train` (or `run`):
  the official `Options` model (3 / 12 layers, 1024 tokens, 256x256), 4 inputs + 4 targets
  (official `num_views` 8), 150k steps (300 epochs x 500 iterations) at lr 4e-4 after 2000
  warm-up steps, batch 64 (8 per GPU x 8), MSE + 0.2 SSIM. The `paper-{2,4,6}view` finetunes start
  from its weights.
- `paper-latent-{2,4,6}view-{ssim,lpips}`: the official 2026.6 latent-bottleneck release
  (`finetune_dl3dv_latent_<N>view_<loss>` under `finetune`, `eval_dl3dv_latent_<N>view_<loss>`
  under `eval`): the `dl3dv_latent_<N>view` model, 6 / 4 / 4 targets (official 8 / 8 / 10
  views), the SSIM variant's loss 0.8 L1 + 0.2 SSIM or the LPIPS variant's MSE + 0.5 LPIPS,
  cameras in the `mean_cam` frame (`--normalization`), and scene-latent tuning at lr 1e-2 when
  evaluating.
"""

from __future__ import annotations

import dataclasses

from experiments.cli import main
from experiments.config import (
  LPIPS_LOSS,
  SSIM_LOSS,
  SYNTHETIC_MODEL,
  EvalSettings,
  Experiment,
  TrainSettings,
)
from tokengs_jax import model

# official (num_input_views, num_views) of the latent release presets
_LATENT_VIEWS = {2: 8, 4: 8, 6: 10}

PRESETS = {}
for _views in (2, 4, 6):
  PRESETS[f"synthetic-{_views}view"] = Experiment(
    dataset="re10k",
    output_dir=f"outputs/dl3dv/synthetic_{_views}view",
    model=SYNTHETIC_MODEL.replace(num_input_views=_views),
    train=TrainSettings(min_context_gap=10, max_context_gap=16),
    eval=EvalSettings(context_gap=16),
  )
  PRESETS[f"paper-{_views}view"] = Experiment(
    dataset="dl3dv",
    data_dir="datasets/dl3dv",
    output_dir=f"outputs/dl3dv/paper_{_views}view",
    model=model.preset(f"dl3dv_{_views}view"),
    train=TrainSettings(
      steps=10_000,
      batch_size=64,
      learning_rate=4e-5,
      warmup_steps=400,
      log_every=50,
      checkpoint_every=2_000,
      num_workers=8,
    ),
    eval=EvalSettings(num_scenes=0, num_target_views=8, grid_scenes=8, video_frames=96),
  )
  for _name, _loss in (("ssim", SSIM_LOSS), ("lpips", LPIPS_LOSS)):
    _paper = PRESETS[f"paper-{_views}view"]
    PRESETS[f"paper-latent-{_views}view-{_name}"] = dataclasses.replace(
      _paper,
      output_dir=f"outputs/dl3dv/paper_latent_{_views}view_{_name}",
      model=model.preset(f"dl3dv_latent_{_views}view"),
      normalization="mean_cam",  # official `_LATENT_D12_ARCH` (issue 26)
      train=dataclasses.replace(
        _paper.train, num_target_views=_LATENT_VIEWS[_views] - _views, **_loss
      ),
      eval=dataclasses.replace(_paper.eval, tuning_target="latents", tuning_learning_rate=1e-2),
    )

# Official `train_dl3dv_base`: the `Options` defaults (model, loss, 4 of 8 views, lr 4e-4) with
# 300 epochs x 500 iterations and 2000 warm-up steps; the global batch of 8 GPUs x 8.
PRESETS["paper-base"] = dataclasses.replace(
  PRESETS["paper-4view"],
  output_dir="outputs/dl3dv/paper_base",
  model=model.ModelConfig(num_input_views=4),
  train=dataclasses.replace(
    PRESETS["paper-4view"].train,
    steps=300 * 500,
    num_target_views=4,
    learning_rate=4e-4,
    warmup_steps=2_000,
    checkpoint_every=5_000,
  ),
)

if __name__ == "__main__":
  main(PRESETS, "synthetic-4view", "python -m experiments.dl3dv")
