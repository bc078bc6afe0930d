"""The stages of the method, one module each: the algorithm and the :class:`~quasisim.method.stage.Stage` it
declares as ``STAGE`` (registered in :data:`quasisim.method.registry.STAGES`): ``point_dynamics`` (stage 1),
``contact_curriculum`` (stage 2, with the hand-off between simulators), ``fit_to_target`` (stage 3), ``mpc``
(closed-loop MPC), ``sampling`` (sampling MPC in the target, stage ``sample``), ``quick`` (the cascade's
first step, sampling from the kinematic retarget) and ``selection`` (stage ``select``); ``_common``: what
they share. Their settings are :mod:`quasisim.method.options`."""
