"""What a researcher runs: the RE10K / DL3DV / Kubric entry points and the paper's studies.

    python -m experiments.re10k                  # synthetic default: generate, train tiny, evaluate
    python -m experiments.re10k eval --data-dir /data/re10k --preset paper \\
        --official-checkpoint tokengs_re10k.safetensors
    python -m experiments.studies.camera_noise
"""
