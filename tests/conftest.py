import os

import pytest


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory):
    """A small synthetic multi-view head dataset, generated once per test session."""
    from progressive_avatars.core.synthetic.dataset import make_dataset

    out = tmp_path_factory.mktemp("synthetic")
    make_dataset(str(out), resolution=40, cameras=5, sequences=3, frames=2, seed=0, progress=False)
    return str(out)


@pytest.fixture(scope="session")
def tiny_run(tiny_dataset, tmp_path_factory):
    """A run trained with the tiny preset on the tiny dataset (shared by stream/eval tests)."""
    from progressive_avatars.core.train.trainer import Trainer, config_for

    out = str(tmp_path_factory.mktemp("run"))
    Trainer(tiny_dataset, out, config_for("tiny")).run(progress=False)
    assert os.path.exists(os.path.join(out, "avatar.npz"))
    return out


@pytest.fixture
def own_tmp(tmp_path, monkeypatch):
    """tempfile's folder for this test: the temporary folders a job leaves behind show up here."""
    import tempfile

    d = tmp_path / "tmp"
    d.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(d))
    return d
