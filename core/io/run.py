"""A training run folder and what is derived from it (importance, stream order, stream file).

RUN/avatar.npz      the trained avatar (creation order)
RUN/importance.npz  face importance over the training views (cached with its key, same order; per level)
RUN/importance_whole.npz  the same measured on the whole avatar (the importance-only ablation)
RUN/avatar.pavs     the progressive stream (docs/FORMAT.md)
RUN/flame_refined.npz  the refined FLAME parameters of the training timesteps (--refine-flame)
"""

from __future__ import annotations

import json
import os
import sys
from contextlib import contextmanager

import numpy as np

from ..avatar.avatar import Avatar
from .safe_io import file_digest


def load_run_avatar(run: str) -> Avatar:
    """RUN/avatar.npz, with the content hash of the bytes it was read from (``source_digest``):
    what run_importance keys its cache on, so a training that replaces the file meanwhile cannot
    file this avatar's importance under the new one's hash."""
    path = os.path.join(run, "avatar.npz")
    holder = training_holder(run)
    if not os.path.exists(path):
        if holder:
            raise FileNotFoundError(f"{path}: no trained avatar yet: this run is being trained ({holder})")
        raise FileNotFoundError(f"{path}: no trained avatar in this run folder (train with scripts/train.py first)")
    for _ in range(3):
        before = file_digest(path)
        avatar = Avatar.load(path)
        if file_digest(path) == before:  # (replaced between the two: read again)
            avatar.source_digest = before
            if holder:
                it = avatar.meta.get("iterations")
                print(
                    f"note: {run} is being trained ({holder}): this uses its avatar.npz as it is now"
                    + (f" ({it} iterations)" if isinstance(it, int) else ""),
                    file=sys.stderr,
                )
            return avatar
    raise ValueError(f"{path} changed each time it was read: a training is writing it; try again once it has finished")


def training_holder(run: str) -> str | None:
    """Who trains ``run`` now (the text of RUN/.train.lock while another process holds it,
    core/train/distributed.run_lock), else None."""
    path = os.path.join(run, ".train.lock")
    try:
        import fcntl
    except ImportError:  # no flock (Windows): no lock to ask
        return None
    try:
        with open(path) as fh:
            try:
                fcntl.flock(fh.fileno(), fcntl.LOCK_SH | fcntl.LOCK_NB)
            except OSError:
                holder = fh.read().strip() or "another process"
                return None if holder.startswith(f"pid {os.getpid()} ") else holder  # (this process's own)
    except OSError:  # no lock file: never trained here
        return None
    return None


class FolderBusyError(RuntimeError):
    """Another process holds a folder's lock (folder_lock): a training of the run, an evaluation
    writing the report folder."""


@contextmanager
def folder_lock(folder: str, name: str, busy, remove: bool = False):
    """Hold FOLDER/NAME (the kernel's flock, so a killed holder leaves no stale lock) for the body,
    the file naming this process; held by another process, FolderBusyError(busy(its text)). The
    exclusive lock is retried for a second: a reader asking who holds it (training_holder) takes
    a shared lock for a moment, which must not refuse a start. ``remove``: the file goes when the
    body ends (a holder that waited on the removed file takes the new one). No flock (Windows):
    no lock."""
    import time

    os.makedirs(folder, exist_ok=True)
    try:
        import fcntl
    except ImportError:
        yield
        return
    path = os.path.join(folder, name)
    end = time.monotonic() + 1.0
    while True:
        fh = open(path, "a+")
        try:
            fcntl.flock(fh.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            if time.monotonic() >= end:
                fh.seek(0)
                holder = fh.read().strip() or "unknown"
                fh.close()
                raise FolderBusyError(busy(holder)) from None
            fh.close()
            time.sleep(0.05)
            continue
        try:
            if os.stat(path).st_ino == os.fstat(fh.fileno()).st_ino:
                break
        except FileNotFoundError:
            pass
        fh.close()  # locked a file its holder had removed meanwhile
    try:
        fh.seek(0)
        fh.truncate()
        fh.write(f"pid {os.getpid()} on {os.uname().nodename if hasattr(os, 'uname') else 'this host'}\n")
        fh.flush()
        yield
    finally:
        if remove:
            try:
                os.remove(path)  # while still held: nobody can hold it as it goes
            except OSError:
                pass
        fh.close()


def run_config(run: str) -> dict | None:
    """RUN/config.json as a dict (None when the run has none). A file that cannot be read, is
    not JSON (a truncated write) or is not a JSON object is a ValueError naming the file."""
    cfg = os.path.join(run, "config.json")
    if not os.path.exists(cfg):
        return None
    from .safe_io import loads_json, read_bounded

    try:
        out = loads_json(read_bounded(cfg, 1 << 24, "config"), cfg)
    except OSError as exc:
        raise ValueError(f"{cfg}: cannot be read ({exc.strerror or exc})") from None
    except ValueError as exc:
        msg = str(exc)
        raise ValueError(msg if msg.startswith(cfg) else f"{cfg}: not valid JSON ({msg})") from None
    if not isinstance(out, dict):
        raise ValueError(f"{cfg}: not a JSON object (a {type(out).__name__}); the run's configuration is damaged")
    return out


def run_data_dir(run: str, data: str | None = None) -> str:
    if data:
        return data
    cfg = run_config(run)
    if cfg is None:
        raise ValueError(f"{run}: no --data given and no config.json naming the dataset")
    where = os.path.join(run, "config.json")
    if "data" not in cfg:
        raise ValueError(f'{where}: no "data" entry naming the dataset; pass --data DIR')
    if not isinstance(cfg["data"], str) or not cfg["data"]:
        raise ValueError(f'{where}: "data" is {cfg["data"]!r}, not a dataset folder; pass --data DIR')
    return cfg["data"]


def run_flame_model(run: str, flame_model: str | None = None) -> str | None:
    """The FLAME model a run trained with (FLAME-mode datasets), unless one is given."""
    if flame_model:
        return flame_model
    cfg = run_config(run)
    fm = None if cfg is None else cfg.get("flame_model")
    if fm is not None and not isinstance(fm, str):
        raise ValueError(f'{os.path.join(run, "config.json")}: "flame_model" is {fm!r}, not a file path')
    return fm or None


def _check_refined_pair(run: str, refined: str) -> None:
    """avatar.npz and flame_refined.npz of one training: a run stopped between writing them
    leaves one without the other, or another iteration's (a resumed run), and the frames would
    be posed unlike training posed them."""
    from .safe_io import check_npz

    avatar = os.path.join(run, "avatar.npz")
    try:
        check_npz(avatar, allow_text=("meta_json",))
        with np.load(avatar, allow_pickle=False) as z:
            meta = json.loads(str(z["meta_json"])) if "meta_json" in z.files else {}
        cfg = meta.get("config") or {}
        trained = meta.get("iterations") if cfg.get("refine_flame") else None
    except Exception:
        return  # loading the avatar reports a damaged one
    fix = "train.py --resume with the run's options writes both again"
    if trained is None:
        return
    if not os.path.exists(refined):
        raise ValueError(
            f"{avatar} was trained with --refine-flame but {refined} is missing (the run stopped while saving): {fix}"
        )
    try:
        with np.load(refined, allow_pickle=False) as z:
            it = int(z["iteration"]) if "iteration" in z.files else None  # (older files: no record)
    except Exception:
        return  # use_refined_flame reports a damaged file
    if it is not None and it != trained:
        raise ValueError(
            f"{refined} holds the FLAME corrections of iteration {it}, {avatar} is of iteration {trained} "
            f"(the run stopped while saving): {fix}"
        )


def run_dataset(run: str, data: str, split: str | None, flame_model: str | None = None, **options):
    """A split of the run's data posed as the run was trained: after ``--refine-flame`` the
    timesteps it refined (the training ones, so the novel views too) take the refined FLAME
    parameters of RUN/flame_refined.npz; the others (novel expressions) stay as tracked."""
    from .dataset import Dataset

    ds = Dataset(data, split, flame_model=flame_model, **options)
    path = os.path.join(run, "flame_refined.npz")
    if ds.mode != "flame":
        return ds
    trained_on = (run_config(run) or {}).get("data")
    if isinstance(trained_on, str) and os.path.realpath(trained_on) != os.path.realpath(data):
        if os.path.exists(path):  # its timesteps are another dataset's: the same ids would pose other frames
            print(
                f"note: {path} refines the frames of {trained_on}, not of {data}: they are posed as tracked",
                file=sys.stderr,
            )
        return ds
    _check_refined_pair(run, path)
    if os.path.exists(path):
        ds.use_refined_flame(path)
    return ds


def run_importance(
    run: str,
    avatar: Avatar,
    data: str,
    max_views: int | None = 120,
    progress=True,
    per_level: bool = True,
    weighting: str = "residual",
    flame_model: str | None = None,
) -> np.ndarray:
    """Importance per face (core/render/importance.py; ``per_level`` False: measured on the whole
    avatar, the paper's, plain alpha*T), computed once per trained avatar, kind and view count and
    cached in the run folder (importance.npz; importance_alpha.npz for per-level plain alpha*T;
    importance_whole.npz). Each cache holds its key with it: the avatar file's and the training
    split's content hashes, the data folder, the FLAME model, max_views and the kind, so a copied
    or restored avatar, an edited dataset or an interrupted write never hands back another
    avatar's importance. ``flame_model``: the run's own (config.json) when not given."""
    if not per_level:
        weighting = "alpha"
    name = "importance_whole" if not per_level else "importance" if weighting == "residual" else "importance_alpha"
    path = os.path.join(run, name + ".npz")
    model = run_flame_model(run, flame_model)
    key = {
        "max_views": max_views,
        "data": os.path.abspath(data),
        "per_level": per_level,
        "weighting": weighting,
        "avatar": getattr(avatar, "source_digest", None) or file_digest(os.path.join(run, "avatar.npz")),
        "train_split": file_digest(os.path.join(data, "transforms_train.json")),
        "flame_model": os.path.abspath(model) if model else None,
    }
    refined = os.path.join(run, "flame_refined.npz")
    if os.path.exists(refined):  # the training meshes it measures on
        key["flame_refined"] = file_digest(refined)
    if os.path.exists(path):
        try:  # a cache: one that is damaged (truncated, garbage) or does not fit is recomputed
            with np.load(path, allow_pickle=False) as z:
                cached, W = json.loads(str(z["key"])), z["W"]
        except Exception:
            cached, W = None, None
        if cached == key and isinstance(W, np.ndarray) and W.shape == (avatar.num_gaussians,) and W.dtype.kind == "f":
            return W
    from ..render.importance import face_importance

    W = face_importance(
        avatar,
        run_dataset(run, data, "train", model, cache_images=0),  # each image is read once
        max_views=max_views,
        progress=progress,
        per_level=per_level,
        weighting=weighting,
    )
    from .atomic import atomic_savez

    atomic_savez(path, W=W, key=np.array(json.dumps(key, sort_keys=True)))
    return W
