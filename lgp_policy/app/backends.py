"""Where evaluation episodes run: ``"local"`` (this process, or a pool of worker processes) or
``"ray"`` (tasks on a Ray cluster, optional extra: ``pip install -e ".[ray]"``).

Every backend runs the same :func:`lgp_policy.rollout.run_episode` on the same seeds, and an
episode depends on its seed alone (each worker reuses one env; ``reset(seed=...)`` fixes the
layout), so the records are bit-identical whatever the backend, the number of workers or the
chunking. Seeds are sent in chunks (one pool job or one Ray task per chunk) so that the per-task
overhead stays small against the episodes' cost (``benchmarks/ray_overhead.py``). Each worker
limits BLAS (and torch, when loaded) to one thread: a worker is one core's worth of work, and the
policy's GP algebra is on small matrices where extra threads only spin.
"""

from __future__ import annotations

import argparse
import math
import os
import signal
import socket
import sys
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

from lgp_policy.rollout import run_episode

__all__ = [
    "BACKENDS",
    "EnvFactory",
    "EpisodeJob",
    "add_backend_arguments",
    "check_backend",
    "chunk_seeds",
    "map_tasks",
    "one_thread",
    "start_episodes",
]

BACKENDS = ("local", "ray")
"""The backends :func:`start_episodes` accepts."""

CHUNKS_PER_WORKER = 4
"""Default chunking: about this many chunks per worker (load balance vs per-chunk overhead)."""


@dataclass(frozen=True)
class EnvFactory:
    """A picklable env constructor: ``gym.make(env_id, **env_kwargs, **extra)``.

    ``env_id`` is a registered Gymnasium id or a level name of ``gym_coffee.LEVELS``
    (``"easy"``, ``"hard"``); ``env_kwargs`` are the constructor keywords (``action_type``,
    ``obs_noise``, ``calibration_bias``, ``cup_push``, ...).
    """

    env_id: str
    env_kwargs: Mapping[str, Any] = field(default_factory=dict)

    def __call__(self, **extra: Any) -> Any:
        import gymnasium as gym

        import gym_coffee

        env_id = getattr(gym_coffee, "LEVELS", {}).get(self.env_id, self.env_id)
        return gym.make(env_id, **{**dict(self.env_kwargs), **extra})


def chunk_seeds(seeds: Sequence[int], n_chunks: int) -> list[list[int]]:
    """Split ``seeds`` into ``min(n_chunks, len(seeds))`` contiguous chunks whose sizes differ
    by at most one (so that the workers' shares stay even)."""
    seeds = [int(s) for s in seeds]
    n_chunks = max(1, min(int(n_chunks), len(seeds)))
    base, extra = divmod(len(seeds), n_chunks)
    out, i = [], 0
    for c in range(n_chunks):
        size = base + (c < extra)
        out.append(seeds[i : i + size])
        i += size
    return out


def _limit_threads() -> Any:
    """One BLAS (and torch) thread in this worker process; returns the threadpoolctl limiter."""
    from threadpoolctl import threadpool_limits

    limiter = threadpool_limits(limits=1, user_api="blas")
    torch = sys.modules.get("torch")
    if torch is not None:
        torch.set_num_threads(1)
    return limiter


@contextmanager
def one_thread() -> Iterator[None]:
    """One BLAS (and torch) thread for the duration of the block, restored afterwards (for
    work in the caller's own process)."""
    torch = sys.modules.get("torch")
    before = torch.get_num_threads() if torch is not None else None
    with _limit_threads():
        try:
            yield
        finally:
            if torch is not None and before is not None:
                torch.set_num_threads(before)


def _run_seeds(policy: Any, env: Any, seeds: Sequence[int], flags: Sequence[str]) -> list[dict]:
    return [run_episode(policy, env, s, flags=flags).record(flags) for s in seeds]


def _chunk_result(records: list[dict], cpu_start: float) -> dict[str, Any]:
    """What a worker sends back for a chunk: the records, and which process spent how many CPU
    seconds on it (``EpisodeJob.worker_cpu_s``; benchmarks use it)."""
    return {
        "records": records,
        "worker": f"{socket.gethostname()}:{os.getpid()}",
        "cpu_s": time.process_time() - cpu_start,
    }


# ------------------------------------------------------------------------------ local pool
_WORKER: dict[str, Any] = {}


def _pool_init(policy: Any, env_factory: Callable[..., Any]) -> None:
    # Ctrl-C reaches the whole process group: the driver stops the workers (see collect_pool);
    # a worker that caught it would hand it back as a chunk's result and go on with the next
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _WORKER["clock"] = 0.0  # a forked worker's CPU clock starts at 0: its set-up counts too
    _WORKER["limiter"] = _limit_threads()
    _WORKER["policy"] = policy
    _WORKER["env"] = env_factory()


def _pool_chunk(seeds: Sequence[int], flags: Sequence[str]) -> dict[str, Any]:
    start = _WORKER.get("clock", time.process_time())
    out = _chunk_result(_run_seeds(_WORKER["policy"], _WORKER["env"], seeds, flags), start)
    _WORKER["clock"] = time.process_time()
    return out


def _pool_context() -> Any:
    import multiprocessing as mp

    # fork: a worker starts in milliseconds with the policy and the imports already in memory
    # (spawn would re-import PyBullet, Gymnasium and the policy in every worker)
    if "fork" in mp.get_all_start_methods():
        return mp.get_context("fork")
    return mp.get_context()  # pragma: no cover - not Linux


# ------------------------------------------------------------------------------ ray
_RAY_WORKER: dict[str, Any] = {}


def _ray_chunk(refs: Sequence[Any], seeds: Sequence[int], flags: Sequence[str]) -> dict[str, Any]:
    """One Ray task: a chunk of episodes on this worker's cached policy and env.

    ``refs`` is ``[policy_ref, env_factory_ref]`` inside a list, so that Ray hands over the
    references rather than the values: a worker fetches and copies the policy once, not per
    task (the copy is writable; values straight from the object store are read-only arrays, and
    a policy with memory updates its arrays in place), and makes its env once.
    """
    import copy

    import ray

    start = time.process_time()
    policy_ref, factory_ref = refs
    if _RAY_WORKER.get("policy_key") != policy_ref.hex():
        _RAY_WORKER["policy"] = copy.deepcopy(ray.get(policy_ref))
        _RAY_WORKER["policy_key"] = policy_ref.hex()
    if _RAY_WORKER.get("env_key") != factory_ref.hex():
        if "env" in _RAY_WORKER:
            _RAY_WORKER.pop("env").close()
        _RAY_WORKER["limiter"] = _limit_threads()
        _RAY_WORKER["env"] = ray.get(factory_ref)()
        _RAY_WORKER["env_key"] = factory_ref.hex()
    records = _run_seeds(_RAY_WORKER["policy"], _RAY_WORKER["env"], seeds, flags)
    return _chunk_result(records, start)


def _ray_init(address: str | None, workers: int) -> Any:
    try:
        import ray
    except ImportError as exc:  # pragma: no cover - depends on the install
        raise ImportError(
            'backend="ray" needs Ray: pip install -e ".[ray]" (or pip install "ray>=2.9")'
        ) from exc
    if not ray.is_initialized():
        kwargs: dict[str, Any] = {"include_dashboard": False, "log_to_driver": False}
        if address is None and workers > 1:
            kwargs["num_cpus"] = workers
        ray.init(address=address, **kwargs)
    return ray


# ------------------------------------------------------------------------------ the job
@dataclass
class EpisodeJob:
    """Episodes started by :func:`start_episodes`; :meth:`collect` waits for their records."""

    seeds: list[int]
    _collect: Callable[[], list[dict]]
    worker_cpu_s: dict[str, float] = field(default_factory=dict)
    """After :meth:`collect`: CPU seconds each worker process (``host:pid``) spent."""

    def collect(self) -> list[dict[str, Any]]:
        """The episodes' records, in the order of ``seeds``."""
        records: list[dict] = []
        for chunk in self._collect():
            records.extend(chunk["records"])
            w = chunk["worker"]
            self.worker_cpu_s[w] = self.worker_cpu_s.get(w, 0.0) + chunk["cpu_s"]
        order = {s: i for i, s in enumerate(self.seeds)}
        return sorted(records, key=lambda r: order[r["seed"]])


def check_backend(backend: str, workers: int, chunk_size: int | None = None) -> None:
    """Raise ``ValueError`` for an unknown backend or a non-positive worker count/chunk size."""
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise ValueError(f"workers must be an integer >= 1, got {workers!r}")
    if chunk_size is not None and (not isinstance(chunk_size, int) or chunk_size < 1):
        raise ValueError(f"chunk_size must be an integer >= 1 or None, got {chunk_size!r}")


def start_episodes(
    policy: Any,
    env_factory: Callable[..., Any],
    seeds: Sequence[int],
    *,
    flags: Sequence[str],
    workers: int = 1,
    backend: str = "local",
    address: str | None = None,
    chunk_size: int | None = None,
    on_done: Callable[[int], None] | None = None,
) -> EpisodeJob:
    """Start one episode per seed; the work runs while the caller does something else
    (except the serial local case, which runs in :meth:`EpisodeJob.collect`).

    Args:
        policy: SB3-style ``predict``; it is pickled to the workers (pool workers get it by
            fork).
        env_factory: ``env_factory()`` makes an env (e.g. :class:`EnvFactory`); each worker
            makes one and reuses it.
        seeds: one episode per seed.
        flags: ``info`` flags to record (see :func:`lgp_policy.rollout.run_episode`).
        workers: ``"local"``: processes (1 = this process); ``"ray"``: the number of CPUs of
            the local Ray instance started when ``address`` is None (an existing cluster's
            size is its own).
        backend: ``"local"`` or ``"ray"``.
        address: the Ray cluster (``"auto"``, ``"ray://host:10001"``, ...); None starts a
            local instance (unless Ray is already initialised in this process).
        chunk_size: seeds per job/task (default: about ``CHUNKS_PER_WORKER`` chunks per
            worker).
        on_done: called with the number of episodes that just finished (progress bars).
    """
    check_backend(backend, workers, chunk_size)
    seeds = [int(s) for s in seeds]
    flags = tuple(flags)
    done = on_done or (lambda n: None)
    if not seeds:
        return EpisodeJob([], list)

    if backend == "ray":
        ray = _ray_init(address, workers)
        n_cpus = max(1, int(ray.cluster_resources().get("CPU", workers)))
        chunks = _chunks(seeds, n_cpus, chunk_size)
        remote = ray.remote(num_cpus=1)(_ray_chunk)
        policy_ref, factory_ref = ray.put(policy), ray.put(env_factory)
        refs = [policy_ref, factory_ref]  # in a list: the tasks get the references
        pending = [remote.remote(refs, c, flags) for c in chunks]

        def collect_ray() -> list[dict]:
            out: list[dict] = []
            todo = list(pending)
            try:
                while todo:
                    ready, todo = ray.wait(todo, num_returns=1)
                    for ref in ready:
                        chunk = ray.get(ref)
                        out.append(chunk)
                        done(len(chunk["records"]))
            except BaseException:  # Ctrl-C or a failed task: cancel what is left
                for ref in todo:
                    ray.cancel(ref, force=True)
                raise
            return out

        return EpisodeJob(seeds, collect_ray)

    if workers == 1 or len(seeds) == 1:

        def collect_serial() -> list[dict]:
            env = env_factory()
            out: list[dict] = []
            try:
                with one_thread():
                    for s in seeds:
                        start = time.process_time()
                        out.append(_chunk_result(_run_seeds(policy, env, [s], flags), start))
                        done(1)
            finally:
                env.close()
            return out

        return EpisodeJob(seeds, collect_serial)

    n_proc = min(workers, len(seeds))
    pool = ProcessPoolExecutor(
        max_workers=n_proc,
        mp_context=_pool_context(),
        initializer=_pool_init,
        initargs=(policy, env_factory),
    )
    futures: list[Future] = [
        pool.submit(_pool_chunk, c, flags) for c in _chunks(seeds, n_proc, chunk_size)
    ]

    def collect_pool() -> list[dict]:
        out: list[dict] = []
        try:
            todo = set(futures)
            while todo:
                ready, todo = wait(todo, return_when=FIRST_COMPLETED)
                for f in ready:
                    chunk = f.result()
                    out.append(chunk)
                    done(len(chunk["records"]))
        except BaseException:  # Ctrl-C or a failed chunk: stop the workers now, not after
            for proc in list(getattr(pool, "_processes", {}).values()):
                proc.terminate()
            pool.shutdown(wait=False, cancel_futures=True)
            raise
        pool.shutdown(wait=True)
        return out

    return EpisodeJob(seeds, collect_pool)


def _chunks(seeds: list[int], n_workers: int, chunk_size: int | None) -> list[list[int]]:
    if chunk_size is not None:
        return chunk_seeds(seeds, math.ceil(len(seeds) / chunk_size))
    return chunk_seeds(seeds, CHUNKS_PER_WORKER * n_workers)


def map_tasks(
    fn: Callable[[Any], Any],
    items: Sequence[Any],
    *,
    backend: str = "local",
    address: str | None = None,
    workers: int = 1,
    num_cpus: float = 1,
) -> list[Any]:
    """``[fn(item) for item in items]``, run where ``backend`` says, results in item order.

    For coarse jobs that are not episodes (e.g. one residual fine-tuning per seed): ``"local"``
    runs them here (``workers=1``) or in ``workers`` forked processes; ``"ray"`` runs each as
    a Ray task asking for ``num_cpus`` CPUs (``ray.init(address=address)`` unless Ray is already
    initialised; see :func:`start_episodes`). ``fn`` and the items must be picklable for
    anything but the serial local case.
    """
    check_backend(backend, workers)
    items = list(items)
    if backend == "ray":
        ray = _ray_init(address, workers)
        remote = ray.remote(num_cpus=num_cpus)(fn)
        return list(ray.get([remote.remote(item) for item in items]))
    if workers == 1 or len(items) <= 1:
        return [fn(item) for item in items]
    with ProcessPoolExecutor(
        max_workers=min(workers, len(items)), mp_context=_pool_context(), initializer=_limit_threads
    ) as pool:
        return list(pool.map(fn, items))


def add_backend_arguments(parser: argparse.ArgumentParser) -> None:
    """Add ``--backend {local,ray}``, ``--address ADDR`` and ``--chunk-size N`` to a command
    (``gym-coffee evaluate``); pass them on as ``backend=args.backend,
    address=args.address, chunk_size=args.chunk_size``."""
    from lgp_policy.app._common import positive_int

    g = parser.add_argument_group("where episodes run")
    g.add_argument(
        "--backend",
        choices=BACKENDS,
        default="local",
        help="local: this machine (--workers processes); ray: tasks on a Ray cluster "
        '(pip install -e ".[ray]")',
    )
    g.add_argument(
        "--address",
        default=None,
        help="Ray cluster address (e.g. auto, ray://head:10001); default: start a local Ray "
        "with --workers CPUs",
    )
    g.add_argument(
        "--chunk-size",
        type=positive_int,
        default=None,
        metavar="N",
        help="episodes per job/task (default: about 4 chunks per worker)",
    )
