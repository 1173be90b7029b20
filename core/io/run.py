"""A training run folder and what is derived from it (importance, stream order, stream file).

RUN/avatar.npz      the trained avatar (creation order)
RUN/importance.npy  face importance over the training views (cached, same order)
RUN/avatar.pavs     the progressive stream (docs/FORMAT.md)
"""

from __future__ import annotations

import json
import os

import numpy as np

from ..avatar.avatar import PARAM_NAMES, Avatar


def load_run_avatar(run: str) -> Avatar:
    path = os.path.join(run, "avatar.npz")
    if not os.path.exists(path):
        raise FileNotFoundError(f"{path}: no trained avatar in this run folder (train with scripts/train.py first)")
    return Avatar.load(path)


def run_data_dir(run: str, data: str | None = None) -> str:
    if data:
        return data
    cfg = os.path.join(run, "config.json")
    if os.path.exists(cfg):
        with open(cfg) as fh:
            return json.load(fh)["data"]
    raise ValueError(f"{run}: no --data given and no config.json naming the dataset")


def run_flame_model(run: str, flame_model: str | None = None) -> str | None:
    """The FLAME model a run trained with (FLAME-mode datasets), unless one is given."""
    if flame_model:
        return flame_model
    cfg = os.path.join(run, "config.json")
    if os.path.exists(cfg):
        with open(cfg) as fh:
            return json.load(fh).get("flame_model")
    return None


def run_importance(run: str, avatar: Avatar, data: str, max_views: int | None = 120, progress=True) -> np.ndarray:
    """Importance per face, computed once per trained avatar and cached in the run folder."""
    path = os.path.join(run, "importance.npy")
    stamp = os.path.getmtime(os.path.join(run, "avatar.npz"))
    if os.path.exists(path) and os.path.getmtime(path) >= stamp:
        W = np.load(path)
        if W.shape == (avatar.num_gaussians,):
            return W
    from .data import Dataset
    from ..render.importance import face_importance

    W = face_importance(avatar, Dataset(data, "train", flame_model=run_flame_model(run)), max_views=max_views,
                        progress=progress)
    tmp = path + ".tmp.npy"
    np.save(tmp, W)
    os.replace(tmp, path)
    return W


def reordered(avatar: Avatar, order: np.ndarray) -> Avatar:
    """The avatar with faces permuted (new face i = old face order[i])."""
    return Avatar(avatar.forest.reorder(order), *(getattr(avatar, n)[order] for n in PARAM_NAMES), meta=avatar.meta,
                  f_rest=avatar.f_rest[order])
