"""Thread budgets for stage processes (humanvdm_core.workflow.threads)."""

import os

from humanvdm_core.workflow.threads import THREAD_VARS, available_cores, stage_threads, thread_env


def test_available_cores_follows_affinity():
    assert available_cores() == len(os.sched_getaffinity(0))


def test_stage_threads_divides_cores_among_jobs_and_honours_override():
    cores = available_cores()
    assert stage_threads(1) == cores
    assert stage_threads(cores * 4) == 1
    assert stage_threads(1, threads=3) == 3


def test_thread_env_sets_counts_and_passive_waiting_without_clobbering_the_user():
    env = thread_env(2, {"OMP_NUM_THREADS": "5"})
    assert env["OMP_NUM_THREADS"] == "5"  # the user's own setting wins ...
    assert all(env[v] == "2" for v in THREAD_VARS if v != "OMP_NUM_THREADS")
    assert env["OMP_WAIT_POLICY"] == "PASSIVE"
    assert thread_env(2, {"OMP_NUM_THREADS": "5"}, override=True)["OMP_NUM_THREADS"] == "2"  # ... unless --threads
