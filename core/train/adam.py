"""Adam for the avatar's parameters: per-row step counts, so rows added by a split start their
own bias correction; on the CPU one compiled pass over all of them.

The torch version (kept for tensors on a GPU, and as the tests' reference) costs eight
elementwise passes over memory per parameter, plus a torch sum for each of the trainer's finite
checks of a gradient and of a parameter: about an eighth of a cpu-preset training step
(docs/BENCHMARKS.md, "Training iteration", the Adam line). The compiled pass does the same
float32 operations in the same order and counts the non-finite values it meets, so the checks
come with it.
"""

from __future__ import annotations

import numpy as np
import torch
from numba import njit, prange

from ..render.kernels import _PARALLEL  # only explicit prange loops run in parallel

_ROWS = 2048  # rows per parallel work item


@njit(cache=True)
def _column_sums(bad):
    # Not bad.sum(axis=0): numba's axis reduction compiles its bounds-check message formatting,
    # seconds of a first run for a sum over a few dozen blocks.
    out = np.zeros(bad.shape[1], np.int64)
    for blk in range(bad.shape[0]):
        for q in range(bad.shape[1]):
            out[q] += bad[blk, q]
    return out


@njit(parallel=_PARALLEL, cache=True)
def count_nonfinite(arrays):
    """NaN and inf values in each of a tuple of [N, K] arrays of N rows (one parallel pass)."""
    n = arrays[0].shape[0]
    blocks = (n + _ROWS - 1) // _ROWS
    bad = np.zeros((blocks, len(arrays)), np.int64)
    for blk in prange(blocks):
        for q in range(len(arrays)):
            a = arrays[q]
            for i in range(blk * _ROWS, min(n, (blk + 1) * _ROWS)):
                for j in range(a.shape[1]):
                    if not np.isfinite(a[i, j]):
                        bad[blk, q] += 1
    return _column_sums(bad)


@njit(parallel=_PARALLEL, cache=True)
def adam_rows(ps, gs, ms, vs, c1, c2, neg_lrs, b1, one_b1, b2, one_b2, eps):
    """One Adam step in place of each parameter ps[q] [N, K_q] (moments ms[q], vs[q]; gradient
    gs[q]; step size -neg_lrs[q]), row i bias-corrected by c1[i] = 1 - b1^t_i and c2[i] =
    1 - b2^t_i. The scalars come in the parameters' dtype, so float32 parameters are stepped in
    float32, with torch's operations in torch's order. One parallel pass for all of them (a
    pass per parameter woke the threads once per parameter). Returns per parameter the number
    of non-finite values the step left in it or in its second moment (a gradient above ~1e20
    overflows v to inf: every later step of that value is then 0, and training goes on frozen)."""
    n = ps[0].shape[0]
    blocks = (n + _ROWS - 1) // _ROWS
    bad = np.zeros((blocks, len(ps)), np.int64)
    for blk in prange(blocks):
        for q in range(len(ps)):
            p, g, m, v, neg_lr = ps[q], gs[q], ms[q], vs[q], neg_lrs[q]
            for i in range(blk * _ROWS, min(n, (blk + 1) * _ROWS)):
                a = c1[i]
                b = c2[i]
                for j in range(p.shape[1]):
                    gi = g[i, j]
                    mi = m[i, j] * b1 + one_b1 * gi
                    vi = v[i, j] * b2 + one_b2 * gi * gi
                    m[i, j] = mi
                    v[i, j] = vi
                    pi = p[i, j] + neg_lr * (mi / a) / (np.sqrt(vi / b) + eps)
                    p[i, j] = pi
                    if not (np.isfinite(pi) and np.isfinite(vi)):  # an inf moment freezes the row silently
                        bad[blk, q] += 1
    return _column_sums(bad)


def _bias_corrections(t: np.ndarray, b1: float, b2: float, dtype=np.float32):
    """(1 - b1^t, 1 - b2^t) per row, in ``dtype``, the powers taken in float64 once per run of
    equal step counts: rows come in blocks that were added together, so there are few runs,
    and two powers per row cost more than the update of a three-column parameter."""
    starts = np.flatnonzero(np.concatenate([[True], t[1:] != t[:-1]]))
    lengths = np.diff(np.append(starts, len(t)))
    ts = t[starts]
    return (
        np.repeat((1 - b1**ts).astype(dtype), lengths),
        np.repeat((1 - b2**ts).astype(dtype), lengths),
    )


def _rows(t: torch.Tensor) -> np.ndarray:
    """A CPU tensor as a [N, K] numpy view of its memory (a 1-D tensor as [N, 1])."""
    a = t.detach().numpy()
    return a.reshape(len(a), -1)


class Adam:
    """Adam with per-row step counts, so rows added by a split start their own bias correction."""

    def __init__(self, params: dict, lrs: dict, betas=(0.9, 0.999), eps=1e-15):
        self.lrs = dict(lrs)
        self.betas, self.eps = betas, eps
        self.m = {k: torch.zeros_like(v) for k, v in params.items()}
        self.v = {k: torch.zeros_like(v) for k, v in params.items()}
        self.steps = torch.zeros(len(next(iter(params.values()))), dtype=torch.float64)

    def _compiled(self, params: dict) -> bool:
        """Whether the compiled pass takes these parameters: CPU, contiguous, one float dtype,
        a row per step count (as the avatar's are)."""
        dtypes = {p.dtype for p in params.values()}
        return (
            len(dtypes) == 1
            and dtypes <= {torch.float32, torch.float64}
            and all(
                p.device.type == "cpu"
                and len(p) == len(self.steps)
                and all(t.is_contiguous() and t.dtype == p.dtype for t in (p, self.m[k], self.v[k]))
                for k, p in params.items()
            )
        )

    def nonfinite_gradients(self, params: dict) -> list:
        """Names of the parameters whose gradient holds a NaN or an inf."""
        named = {k: p.grad for k, p in params.items() if p.grad is not None}
        if not named:
            return []
        if self._compiled(params):  # torch keeps a gradient in its parameter's dtype
            counts = count_nonfinite(tuple(_rows(g.contiguous()) for g in named.values()))
            return [k for k, c in zip(named, counts) if c]
        return [k for k, g in named.items() if not bool(torch.isfinite(g).all())]

    @torch.no_grad()
    def step(self, params: dict, lr_scale: dict | None = None) -> list:
        """One step of every parameter that has a gradient (then cleared); returns the names of
        those the step left with a NaN or an inf."""
        b1, b2 = self.betas
        self.steps += 1
        if not self._compiled(params):
            return self._torch_step(params, lr_scale)
        names = [k for k, p in params.items() if p.grad is not None]
        if not names:
            return []
        ps = [params[k] for k in names]
        ty = _rows(ps[0]).dtype.type
        c1, c2 = _bias_corrections(self.steps.numpy(), b1, b2, ty)
        lrs = np.array([-self.lrs[k] * (lr_scale or {}).get(k, 1.0) for k in names], ty)
        counts = adam_rows(
            tuple(_rows(p) for p in ps),
            tuple(_rows(p.grad.contiguous()) for p in ps),
            tuple(_rows(self.m[k]) for k in names),
            tuple(_rows(self.v[k]) for k in names),
            c1,
            c2,
            lrs,
            ty(b1),
            ty(1 - b1),
            ty(b2),
            ty(1 - b2),
            ty(self.eps),
        )
        for p in ps:
            p.grad = None
        return [k for k, c in zip(names, counts) if c]

    @torch.no_grad()
    def _torch_step(self, params: dict, lr_scale: dict | None) -> list:
        """The same step with torch's elementwise operations (parameters on a GPU)."""
        b1, b2 = self.betas
        c1 = (1 - b1**self.steps).to(torch.float32)
        c2 = (1 - b2**self.steps).to(torch.float32)
        finite = {}
        for name, p in params.items():
            if p.grad is None:
                continue
            g = p.grad
            m, v = self.m[name], self.v[name]
            m.mul_(b1).add_(g, alpha=1 - b1)
            v.mul_(b2).addcmul_(g, g, value=1 - b2)
            shape = (-1,) + (1,) * (p.dim() - 1)
            denom = (v / c2.to(v.device).view(shape)).sqrt_().add_(self.eps)
            lr = self.lrs[name] * (lr_scale or {}).get(name, 1.0)
            p.addcdiv_(m / c1.to(m.device).view(shape), denom, value=-lr)
            p.grad = None
            finite[name] = torch.isfinite(p).all() & torch.isfinite(v).all()
        if not finite:
            return []
        flags = torch.stack(list(finite.values())).tolist()  # one wait for a GPU, not one per parameter
        return [name for name, ok in zip(finite, flags) if not ok]

    def grow(self, params: dict):
        """Extend the state for rows appended to the parameters (zero moments, zero steps)."""
        n_old = len(self.steps)
        for name, p in params.items():
            extra = p.shape[0] - self.m[name].shape[0]
            if extra > 0:
                z = torch.zeros((extra,) + tuple(p.shape[1:]), dtype=p.dtype)
                self.m[name] = torch.cat([self.m[name], z])
                self.v[name] = torch.cat([self.v[name], z.clone()])
        n_new = next(iter(params.values())).shape[0]
        if n_new > n_old:
            self.steps = torch.cat([self.steps, torch.zeros(n_new - n_old, dtype=torch.float64)])
