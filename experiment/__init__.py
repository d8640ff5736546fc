"""The experiment harness of `python dagger.py`: everything a run needs that is not the paper's method.

    run_folder.py  runs/<name>/: the loop's memo (Run.memo: a step's result loaded if finished, else computed and
                   written atomically), resume, config mismatch, damaged files named, the seed of every stage,
                   resumable training, the folder's locks (two processes); the episode files, the calibration's JSON
    checkpoints.py policy files: the format, older files' retired fields, damage, the training state (AdamW, random
                   streams, the sampler's pool) a stopped training resumes from
    workers.py     the loop's map (worker_map): the arms of a round in worker processes, the BC row beside the rounds
    cli.py         the command line: profiles, overrides, the run folder's name, Ctrl-C and errors
    profiles.py    the run sizes (smoke, quick, mid, table2, paper) and the config's valid values
    report.py      the command's mode (run_experiment), Table I's assembly (summarize: mean ± SE, the paper's
                   tests that dagger.py hands over in report.Paper), results.json, results.csv, table.md, report.md,
                   the table figures, the paper's figures when their inputs changed
    figures.py     the paper's figures (fig1-fig5) from D0 and lineage 0, round 1
    student_t.py   Student's t distribution (no scipy): the p-values of dagger.paired_ttest and dagger.tost
    cpu_kernels.py eps_theta computed faster, the same function: the FiLM table (the step part of all K steps
                   once per sampling call), oneDNN's product and a closed-form Mish where they pay on a CPU kind
and Table II's env and the research variants, which plug into the core's tables when dagger.py imports them:
    engine3d.py       the UR5 reaching an engine lever (Table II), its kinematics: envs.ENVIRONMENTS['engine3d']
    image_obs.py      the UR5 policy on camera images: envs.ENVIRONMENTS['engine3d_image'] and
                      diffusion.OBS_ENCODERS['image_cnn'] (python dagger.py --env engine3d_image)
    oriented_goal.py  the authors' 10-degree goal posture: envs.ENVIRONMENTS['engine3d_oriented']
    lever.py          the authors' lever recipe: dagger.RECIPES['authors_lever'(_seeds)], diffusion.LR_SCHEDULES
                      ['constant'], padded short interventions (python dagger.py --recipe authors_lever)
    controls.py       rows beside Table I's: the sigma = 0 row zero_noise (dagger.noise_model), HG-DAgger as the
                      authors' kit trained it (authors_hg_dagger) and the paper's text's co-training (cotrain_fixed_8,
                      cotrain_pooled) (dagger.intervention_sampler); all listed in dagger.ALL_METHODS

It imports the concept modules (envs, diffusion, relabel, calibrate) but never dagger.py; dagger.py passes in what it
needs (its profiles, its loop and statistical tests in dagger.PAPER, its worker functions). A student may skip this folder.
"""
