"""The generic DAG engine: pipelines of stage executables over a content-addressed artifact store.

- :mod:`.pipeline`   ``pipeline.yaml``: the DAG, loaded and validated; code fingerprints.
- :mod:`.stage`      the stage executable's contract (``SPEC``, ``run(ctx)``, exit codes).
- :mod:`.store`      the content-addressed artifact store; :mod:`.hashing` its content hashes.
- :mod:`.scheduler`  plans, explains (status) and runs stage runs, with caching and early cutoff.
- :mod:`.executors`  where stage runs execute: local subprocesses or Ray tasks.
- :mod:`.progress`   the progress channel from stage processes, and its display.
- :mod:`.threads`    thread budgets for stage processes; :mod:`.atomic` atomic file writes.
- :mod:`.errors`     user-facing errors; :mod:`.cli` the command line's generic verbs.

Nothing here imports the reconstruction modules of :mod:`humanvdm_core`; they build on this.
"""
