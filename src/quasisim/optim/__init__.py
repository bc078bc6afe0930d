"""Trajectory optimisation in the quasi-physical simulator (optax style: small composable pieces):
decision variables (:mod:`~quasisim.optim.trajectory`), the objective (:mod:`~quasisim.optim.objective`),
the identified parameters S (:mod:`~quasisim.optim.sysid`) and the Adam loop (:mod:`~quasisim.optim.adam`)."""
