"""The experiment harness of `python dagger.py`: everything a run needs that is not the paper's method. It stands
above dagger.py: it imports dagger.py and the concept modules, and none of them imports it.

    cli.py          the command line (`python dagger.py` hands over to cli.main): profiles, overrides, the run
                    folder's name, Ctrl-C and errors
    profiles.py     the run sizes (smoke, quick, mid, table1, table1_strong, table2, paper), the methods and recipes a
                    run may name, and the config's checks (check_config, where a config enters)
    report.py       the command's mode (run_experiment: dagger.policy_calibrated_dagger on a run folder, with what
                    the config's variant hands the loop: loop_arguments), Table I's assembly (summarize: mean ± SE,
                    dagger.py's paired tests), results.json, results.csv, table.md, report.md, the table figures
    run_folder.py   runs/<name>/: the loop's memo (Run.memo: a step's result loaded if finished, else computed and
                    written atomically), resume, config mismatch, damaged files named, resumable training (Run.train:
                    where the CPU kernels are swapped into a policy, and pi_0 gets its 2 torch threads), the folder's
                    locks (two processes); the episode files, the calibration's JSON
    checkpoints.py  policy files: the format, older files' retired fields, damage, the training state (AdamW, random
                    streams, the sampler's pool) a stopped training resumes from
    workers.py      the loop's map (worker_map): the arms of a round in worker processes, the BC row beside the rounds
    figures.py      the paper's figures (fig1-fig5) from D0 and lineage 0, round 1
    cpu_kernels.py  eps_theta computed faster, the same function: the FiLM table (the step part of all K steps once per
                    sampling call), oneDNN's product and a closed-form Mish where they pay on a CPU kind
and Table II's env and the research variants, each bringing its own functions that the harness hands to the loop:
    environments.py   the env factory of every env a run may name (dagger's make_env): planar, engine3d,
                      engine3d_image, engine3d_oriented
    engine3d.py       the UR5 reaching an engine lever (Table II), its kinematics
    image_obs.py      the UR5 policy on camera images: its env and the CNN it names (env.obs_encoder)
    oriented_goal.py  the authors' 10-degree goal posture
    lever.py          the authors' lever recipe (--recipe authors_lever, authors_lever_seeds): a learning-rate
                      function, pi_0 as the BC row, every intervention kept, padded chunks, rounds by frames
    controls.py       rows beside Table I's: zero_noise (sigma = 0), authors_hg_dagger, cotrain_fixed_8, cotrain_pooled,
                      zero_noise_servo, fixed_8_servo, pooled_servo; their sampler (Rows) is the loop's where a config
                      names one
    servo.py          the authors' return label, their clamped servo, its knobs converted from their units (the
                      _servo rows; the paper's PD of relabel.py is every other noised row's)
A student may skip this folder.
"""
