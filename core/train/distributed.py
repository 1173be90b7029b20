"""Data-parallel training over views with torch.distributed (training tier).

Under ``torchrun`` (RANK / WORLD_SIZE / LOCAL_RANK in the environment) every process holds the
whole avatar and renders its own views of each iteration; the trainer averages the parameter
gradients over the ranks, sums the growth statistics, takes the growth decision on rank 0 and
broadcasts it, and compares digests of the forest and of the parameters/optimiser state across
ranks (a mismatch stops training with an error instead of drifting apart silently). Only rank 0
writes the run folder, and it holds a lock on it for the whole run, so two trainings can never
write one folder at once. A plain ``python scripts/train.py`` is world size 1: nothing here
communicates, and the training path is the one it always was.
"""

from __future__ import annotations

import hashlib
import os

import numpy as np

_TIMEOUT_ENV = "PA_DIST_TIMEOUT"  # seconds a collective may wait for a silent rank (default 900)


def _usable_cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def threads_per_rank(local_world_size: int) -> int:
    """cores // processes on this node: N ranks on one machine do not oversubscribe its cores."""
    return max(1, _usable_cores() // max(1, local_world_size))


def digest(*arrays) -> int:
    """A 63-bit digest of arrays' bytes (shape and dtype included), comparable across processes."""
    h = hashlib.sha256()
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(str((a.dtype.str, a.shape)).encode())
        h.update(a.tobytes())
    return int.from_bytes(h.digest()[:8], "little") >> 1


def check_same(what: str, values: list, iteration: int) -> None:
    """Every rank must hold the same `what` (one digest per rank, by rank)."""
    if len(set(values)) > 1:
        by_rank = ", ".join(f"rank {r}: {v:016x}" for r, v in enumerate(values))
        raise RuntimeError(
            f"iteration {iteration}: the ranks hold different {what} ({by_rank}); data-parallel training "
            "cannot continue. Training stopped, the last checkpoint is kept; --resume continues from it"
        )


def collective_timeout() -> float:
    """PA_DIST_TIMEOUT in seconds (900 when unset); anything but a positive number is an error
    (0 or a word made every rank fail in its first collective with a C++ traceback)."""
    text = os.environ.get(_TIMEOUT_ENV, "900")
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not (np.isfinite(value) and value > 0):
        raise ValueError(f"{_TIMEOUT_ENV}={text!r}: must be a positive number of seconds (default 900)")
    return value


class Dist:
    """The process's place in a data-parallel job; world size 1 is a single process (no-ops)."""

    def __init__(self, rank: int = 0, world_size: int = 1, local_world_size: int = 1):
        self.rank, self.world_size, self.local_world_size = int(rank), int(world_size), int(local_world_size)

    @property
    def is_main(self) -> bool:
        return self.rank == 0

    @classmethod
    def from_env(cls, threads: int | None = None) -> "Dist":
        """Join the job torchrun describes in the environment, or world size 1 without one.

        Threads per process: `threads` if given; otherwise cores // processes on this node for
        both torch and numba (torchrun's own OMP_NUM_THREADS=1 default is replaced), except that
        NUMBA_NUM_THREADS set by the user is kept for numba."""
        world = int(os.environ.get("WORLD_SIZE", "1"))
        if world <= 1 or "RANK" not in os.environ:
            if threads:
                _set_threads(threads, threads)
            return cls()
        import datetime

        import torch
        import torch.distributed as td

        local_world = int(os.environ.get("LOCAL_WORLD_SIZE", world))
        n = threads or threads_per_rank(local_world)
        _set_threads(n, threads or (None if "NUMBA_NUM_THREADS" in os.environ else n))
        # The trainer's tensors are CPU tensors (the rasteriser is numba): gloo moves them. On a
        # CUDA build NCCL takes any CUDA tensors a later device path hands it.
        backend = "cpu:gloo,cuda:nccl" if torch.cuda.is_available() and td.is_nccl_available() else "gloo"
        timeout = datetime.timedelta(seconds=collective_timeout())
        if not td.is_initialized():
            td.init_process_group(backend=backend, init_method="env://", timeout=timeout)
        return cls(td.get_rank(), td.get_world_size(), local_world)

    def close(self) -> None:
        if self.world_size > 1:
            import torch.distributed as td

            if td.is_initialized():
                td.destroy_process_group()

    # -- collectives (every rank calls them in the same order) ------------------------------
    def all_reduce_sum_(self, t):
        if self.world_size > 1:
            import torch.distributed as td

            td.all_reduce(t, op=td.ReduceOp.SUM)
        return t

    def sum_arrays_(self, *arrays: np.ndarray) -> None:
        """Sum float64 numpy arrays over the ranks in place (one collective)."""
        self._reduce_arrays_("SUM", arrays)

    def max_arrays_(self, *arrays: np.ndarray) -> None:
        """Element-wise maximum of float64 numpy arrays over the ranks, in place (one collective)."""
        self._reduce_arrays_("MAX", arrays)

    def _reduce_arrays_(self, op: str, arrays) -> None:
        if self.world_size == 1:
            return
        import torch
        import torch.distributed as td

        flat = torch.from_numpy(np.concatenate([np.ravel(a) for a in arrays]).astype(np.float64))
        td.all_reduce(flat, op=getattr(td.ReduceOp, op))
        o = 0
        for a in arrays:
            a.reshape(-1)[:] = flat[o : o + a.size].numpy()
            o += a.size

    def broadcast_ints(self, values: np.ndarray | None) -> np.ndarray:
        """Rank 0's int64 array on every rank (others pass None)."""
        if self.world_size == 1:
            return np.asarray(values, np.int64)
        import torch
        import torch.distributed as td

        n = torch.tensor([len(values) if self.is_main else 0], dtype=torch.int64)
        td.broadcast(n, src=0)
        buf = torch.from_numpy(np.asarray(values, np.int64).copy()) if self.is_main else torch.empty(int(n[0]))
        buf = buf.to(torch.int64)
        td.broadcast(buf, src=0)
        return buf.numpy()

    def gather_digest(self, value: int) -> list:
        if self.world_size == 1:
            return [value]
        import torch
        import torch.distributed as td

        out = [torch.zeros(1, dtype=torch.int64) for _ in range(self.world_size)]
        td.all_gather(out, torch.tensor([value], dtype=torch.int64))
        return [int(t[0]) for t in out]


def _set_threads(torch_threads: int | None, numba_threads: int | None) -> None:
    if torch_threads:
        import torch

        torch.set_num_threads(int(torch_threads))
    if numba_threads:
        import numba

        numba.set_num_threads(min(int(numba_threads), numba.config.NUMBA_NUM_THREADS))


def run_lock(out_dir: str):
    """Hold RUN/.train.lock for the body: a second training of the same run folder (another
    process, another torchrun job without a shared rendezvous) fails at once instead of writing
    over this one. The lock is the kernel's (flock), so a killed holder leaves no stale lock."""
    from ..io.run import folder_lock

    return folder_lock(
        out_dir,
        ".train.lock",
        lambda holder: (
            f"{out_dir} is being trained by another process ({holder}); two trainings must not write one run "
            "folder: wait for it, stop it, or choose another --out (several processes of one job: start them "
            "with torchrun)"
        ),
    )
