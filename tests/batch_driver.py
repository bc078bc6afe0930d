"""``quasisim`` with test hooks in its batches: ``python batch_driver.py HOOKS_JSON batch ARGS...`` runs
``quasisim batch ARGS...`` as ``python -m quasisim.cli`` does, with :data:`quasisim.batch.HOOKS` set to
``batch_hooks.ScriptedHooks(**HOOKS_JSON)`` (carried to the workers with each clip)."""

import json
import sys

import quasisim.batch
from batch_hooks import ScriptedHooks
from quasisim.cli import main

if __name__ == "__main__":
    quasisim.batch.HOOKS = ScriptedHooks(**json.loads(sys.argv[1]))
    main(sys.argv[2:], prog_name="quasisim")
