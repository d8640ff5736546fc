"""A research control: rows that are not the paper's, beside Table I's, to separate what a method's parts do.

    zero_noise   the noised arms' whole pipeline with sigma = 0: every intervention state relabelled by the return
                 labels, no noise. It separates the effect of the noise from that of relabelling (a noised arm
                 never sees the recorded intervention chunks, HG-DAgger sees nothing else). Measured on the lever:
                 benchmarks/README.md, "The σ = 0 control on the lever" (and the mid run's σ = 0 row).

Each row is a (noise kind, sigma) of relabel.AugmentationSampler; dagger.noise_model looks a control's up here and
dagger.ALL_METHODS lists them (`python dagger.py --methods hg_dagger,fixed_4,pooled,zero_noise`). It never imports
dagger.py.
"""
NOISE_MODELS = {"zero_noise": ("isotropic", 0.0)}
