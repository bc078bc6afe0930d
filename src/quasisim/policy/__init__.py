"""Learned tracking policies on quasisim's clips: PPO (stable-baselines3, the optional extra ``rl``) trained in
the tracking environment (:mod:`quasisim.envs`), from scratch (``dgrasp-tracking``) or as a residual on one of
our results (``ours+residual``), and judged like every other result (docs/policies.md).

* :mod:`quasisim.policy.config`: the PPO settings (``configs/ppo.yaml``);
* :mod:`quasisim.policy.train`: training with checkpoints and resume;
* :mod:`quasisim.policy.evaluate`: a trained policy replayed in the target, nominal and in the perturbed worlds;
* :mod:`quasisim.policy.curves`: the learning curves of training runs as a figure.
"""
