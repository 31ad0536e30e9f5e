"""``backend="ray"``: episodes as Ray tasks on a local Ray instance with 2 CPUs give the very
records the local backend gives for the same seeds."""

from __future__ import annotations

import os
import sys

import pytest

ray = pytest.importorskip("ray")

import test_evaluation  # noqa: E402  (this folder is on sys.path: pytest's rootdir-less import)
from test_evaluation import SHORT, MemoryPolicy, ScriptedPolicy  # noqa: E402

from lgp_policy.app.evaluation import evaluate_policy_stages  # noqa: E402


@pytest.fixture(scope="module")
def local_ray():
    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.dirname(__file__))))
    ray.init(
        num_cpus=2,
        include_dashboard=False,
        log_to_driver=False,
        runtime_env={"env_vars": {"PYTHONPATH": root}},  # the workers import this checkout
    )
    # the workers cannot import this test module: its policy class travels by value
    ray.cloudpickle.register_pickle_by_value(sys.modules[test_evaluation.__name__])
    yield
    ray.cloudpickle.unregister_pickle_by_value(sys.modules[test_evaluation.__name__])
    ray.shutdown()


def test_ray_backend_gives_the_local_results(local_ray):
    kw = {"env_kwargs": SHORT, "progress": False, "seed": 2}
    local = evaluate_policy_stages(ScriptedPolicy(), 3, **kw)
    on_ray = evaluate_policy_stages(ScriptedPolicy(), 3, backend="ray", chunk_size=1, **kw)
    assert on_ray["backend"] == "ray"
    assert on_ray["episodes"] == local["episodes"]
    assert on_ray["stages"] == local["stages"]
    # a policy with memory updated in place (read-only arrays straight from the object store)
    local = evaluate_policy_stages(MemoryPolicy(), 3, **kw)
    on_ray = evaluate_policy_stages(MemoryPolicy(), 3, backend="ray", **kw)
    assert on_ray["episodes"] == local["episodes"]


def test_map_tasks_on_ray(local_ray):
    from lgp_policy.app.backends import map_tasks

    assert map_tasks(test_evaluation._square, [-3, 2, -1], backend="ray") == [9, 4, 1]
