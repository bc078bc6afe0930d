"""One module per stage of the method, each declaring its :class:`~quasisim.method.stage.Stage` as ``STAGE``
(registered in :data:`quasisim.method.registry.STAGES`); the algorithms they run live beside them in
:mod:`quasisim.method` (``stage1``, ``stage2``, ``handoff``, ``stage3``, ``mpc``, ``sampling``,
``select``)."""
