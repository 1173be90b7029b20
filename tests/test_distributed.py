"""Data-parallel training under torchrun: 2 CPU processes with gloo on the tiny preset."""

import json
import os
import signal
import subprocess
import sys
import time

import numba
import numpy as np
import pytest
import torch

from progressive_avatars.core.avatar.forest import Forest
from progressive_avatars.core.train.distributed import check_same, digest, run_lock
from progressive_avatars.core.train.trainer import Trainer, config_for

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _torchrun(data, out, *extra, nproc=2, **popen):
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", str(nproc)]
    cmd += [os.path.join(ROOT, "scripts", "train.py"), "--data", data, "--out", str(out), "--preset", "tiny"]
    return cmd + ["--no-progress", *extra]


def _lines(run):
    return [json.loads(line) for line in open(os.path.join(run, "metrics.jsonl"))]


@pytest.mark.slow  # two training processes and a single-process reference
def test_two_ranks_equal_one_process_with_the_same_batch(tiny_dataset, tmp_path):
    """2 ranks x 1 view against 1 process x 2 views (the same effective batch), growth under a size
    floor (split_min_px, the ranks' sizes folded by their maximum): every rank holds
    the same forest after every growth step, and the results agree. Tolerance: forests identical,
    parameters and optimiser moments within 1e-6 absolute. With two ranks every reduction has two
    operands (a + b = b + a, halving is exact) and the per-view losses are scaled by powers of two,
    so the runs are in fact bit-identical here. More ranks sum the growth statistics and gradients
    in another order: the forests and step counts still agree, but rounding-level gradient
    differences become whole learning-rate steps in Adam's first updates, so parameters can
    differ by a few learning rates (measured with 3 ranks: d_log_scale by up to 0.08 after 40
    iterations); that is a different sum, not a different training."""
    run2 = tmp_path / "ranks2"
    # 40 of the tiny preset's 60 iterations (growth at 15 and 30, checkpoints at 20 and 40): test time
    done = subprocess.run(
        _torchrun(tiny_dataset, run2, "--iterations", "40", "--split-min-px", "0.45"),
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    # One thread, as each rank has: the results do not depend on it (the kernels sum in fixed
    # orders), and a loaded machine stalls multi-threaded kernels.
    numba_threads, torch_threads = numba.get_num_threads(), torch.get_num_threads()
    numba.set_num_threads(1)
    torch.set_num_threads(1)
    try:
        one = Trainer(
            tiny_dataset, str(tmp_path / "one"), config_for("tiny", iterations=40, views_per_step=2, split_min_px=0.45)
        )
        one.run(progress=False)
    finally:
        numba.set_num_threads(numba_threads)
        torch.set_num_threads(torch_threads)

    cfg = json.load(open(run2 / "config.json"))
    assert cfg["world_size"] == 2 and cfg["views_per_step"] == 1 and cfg["effective_batch"] == 2
    rows = _lines(run2)
    assert rows and all(r["world_size"] == 2 for r in rows)
    growth = [r for r in rows if "growth" in r]
    assert [r["iteration"] for r in growth] == [15, 30]  # every growth step of the run
    for r in growth:
        by_rank = r["growth"]["forest_digest_by_rank"]
        assert len(by_rank) == 2 and by_rank[0] == by_rank[1], r
    assert sum(r["growth"]["split"] for r in growth) > 0  # the forest did grow

    a, b = np.load(run2 / "checkpoint.npz"), np.load(tmp_path / "one" / "checkpoint.npz")
    f = one.model.forest
    assert growth[-1]["growth"]["forest_digest_by_rank"][0] == f"{digest(f.parent, f.slot):016x}"
    np.testing.assert_array_equal(a["forest_parent"], b["forest_parent"])
    np.testing.assert_array_equal(a["forest_slot"], b["forest_slot"])
    for key in a.files:
        if key.startswith(("param_", "adam_m_", "adam_v_")):
            np.testing.assert_allclose(a[key], b[key], rtol=0, atol=1e-6, err_msg=key)
    np.testing.assert_allclose(a["grad_sum"], b["grad_sum"], rtol=1e-9)  # the ranks' statistics, summed
    np.testing.assert_array_equal(a["grad_count"], b["grad_count"])
    # the projected sizes, the ranks' largest (a floor near the tiny head's median size, so it holds back faces)
    np.testing.assert_array_equal(a["size_px"], b["size_px"])
    ref = {r["iteration"]: r for r in _lines(tmp_path / "one")}
    for r in rows:
        if "loss" in r:
            assert r["loss"] == pytest.approx(ref[r["iteration"]]["loss"], abs=1e-6)
        if "val_psnr" in r:
            assert r["val_psnr"] == pytest.approx(ref[r["iteration"]]["val_psnr"], abs=1e-4)
    assert os.path.exists(run2 / "avatar.npz")


def _worker_pid(launcher: int, rank: int):
    """The pid of torchrun's worker process of `rank` (its children, by RANK in their environment)."""
    for task in os.listdir(f"/proc/{launcher}/task"):
        for pid in open(f"/proc/{launcher}/task/{task}/children").read().split():
            try:
                env = open(f"/proc/{pid}/environ", "rb").read().split(b"\0")
            except OSError:
                continue
            if f"RANK={rank}".encode() in env:
                return int(pid)
    return None


@pytest.mark.slow  # a 2-process job, killed, then resumed by one process
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="finds torchrun's workers in /proc")
def test_killed_rank_stops_the_job_and_one_process_resumes(tiny_dataset, tmp_path):
    run = tmp_path / "killed"
    log = open(tmp_path / "torchrun.log", "w")
    job = subprocess.Popen(_torchrun(tiny_dataset, run, "--iterations", "5000"), stdout=log, stderr=subprocess.STDOUT)
    try:
        deadline = time.time() + 300
        while not (run / "checkpoint.npz").exists():
            assert job.poll() is None and time.time() < deadline, open(tmp_path / "torchrun.log").read()[-3000:]
            time.sleep(0.2)
        victim = _worker_pid(job.pid, 1)
        assert victim is not None
        os.kill(victim, signal.SIGKILL)
        t0 = time.time()
        rc = job.wait(timeout=120)  # the survivor must not wait for the dead rank
        stopped_after = time.time() - t0
    finally:
        if job.poll() is None:
            job.kill()
            job.wait()
    text = open(tmp_path / "torchrun.log").read()
    assert rc != 0 and stopped_after < 60
    # The surviving rank says what happened (or torchrun's report names the killed rank, when it
    # stopped the survivor first).
    assert "another process of this torchrun job died" in text or "stopped by the launcher" in text, text[-3000:]
    assert "Signal 9 (SIGKILL)" in text

    # The last checkpoint is intact: it loads, and it is a checkpoint iteration of a 2-rank job.
    with np.load(run / "checkpoint.npz", allow_pickle=False) as d:
        Forest.from_state(d)
        state = json.loads(str(d["state_json"]))
    assert state["world_size"] == 2 and state["iteration"] % 20 == 0 and state["iteration"] >= 20

    # One process resumes the 2-rank checkpoint and trains on.
    it = state["iteration"]
    cfg = config_for("tiny", iterations=it + 10, eval_every=10**6)
    resumed = Trainer(tiny_dataset, str(run), cfg, resume=True)
    assert resumed.iteration == it and resumed.model.num_faces == len(state_faces(run))
    resumed.run(progress=False)
    assert resumed.iteration == it + 10
    assert json.load(open(run / "config.json"))["world_size"] == 1
    rows = _lines(run)
    assert {r["world_size"] for r in rows if r["iteration"] <= it} == {2}
    assert {r["world_size"] for r in rows if r["iteration"] > it} == {1}
    assert rows[-1]["iteration"] == it + 10 and np.isfinite(rows[-1]["loss"])


@pytest.mark.slow  # a two-process job that stops at its start
def test_ranks_started_with_other_options_are_refused(tiny_dataset, tmp_path):
    """One rank given another seed (a node's command line edited) would train neither run:
    refused before the first step, saying what to do."""
    wrapper = tmp_path / "wrapper.py"
    wrapper.write_text(
        "import os, runpy, sys\n"
        "if os.environ.get('RANK') == '1':\n"
        "    sys.argv += ['--seed', '5']\n"
        f"sys.argv[0] = {os.path.join(ROOT, 'scripts', 'train.py')!r}\n"
        "runpy.run_path(sys.argv[0], run_name='__main__')\n"
    )
    cmd = _torchrun(tiny_dataset, tmp_path / "run", "--iterations", "20")
    cmd[cmd.index(os.path.join(ROOT, "scripts", "train.py"))] = str(wrapper)
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert done.returncode != 0
    assert "rank(s) 1 were started with other training options or data than rank 0" in done.stderr, done.stderr[-3000:]
    assert not (tmp_path / "run" / "avatar.npz").exists() and not (tmp_path / "run" / "checkpoint.npz").exists()


def state_faces(run):
    with np.load(run / "checkpoint.npz") as d:
        return d["forest_parent"]


def test_run_folder_lock_and_rank_disagreement_errors(tmp_path):
    """Two trainings of one run folder: the second is refused at once (the lock is the kernel's,
    so a killed holder leaves none behind); ranks holding different states stop with an error."""
    out = str(tmp_path / "run")
    with run_lock(out):
        with pytest.raises(RuntimeError, match="being trained by another process"):
            with run_lock(out):
                pass
        # The entry point refuses before touching the folder (exit 2, the holder named).
        cmd = [sys.executable, os.path.join(ROOT, "scripts", "train.py"), "--data", str(tmp_path / "no-data")]
        done = subprocess.run(cmd + ["--out", out, "--preset", "tiny"], capture_output=True, text=True, timeout=300)
        assert done.returncode == 2 and f"pid {os.getpid()}" in done.stderr, done.stderr
        assert os.listdir(out) == [".train.lock"]
    with run_lock(out):  # released: the next training takes it
        pass
    # A reader asking whether the run is being trained (a shared lock for a moment) does not
    # refuse a training that starts meanwhile.
    import fcntl
    import threading

    with open(os.path.join(out, ".train.lock")) as reader:
        fcntl.flock(reader.fileno(), fcntl.LOCK_SH)
        threading.Timer(0.3, fcntl.flock, (reader.fileno(), fcntl.LOCK_UN)).start()
        with run_lock(out):
            pass
    # A collective timeout that is not a positive number is refused before joining the job.
    env = dict(os.environ, WORLD_SIZE="2", RANK="0", LOCAL_WORLD_SIZE="2", MASTER_ADDR="127.0.0.1", MASTER_PORT="1")
    for bad in ("abc", "0", "-5", "nan"):
        done = subprocess.run(
            [sys.executable, os.path.join(ROOT, "scripts", "train.py"), "--data", out, "--out", out + "_x"],
            env=dict(env, PA_DIST_TIMEOUT=bad),
            capture_output=True,
            text=True,
            timeout=300,
        )
        assert done.returncode == 2 and f"PA_DIST_TIMEOUT='{bad}': must be a positive number" in done.stderr, (
            bad,
            done.stderr[-2000:],
        )
        assert "Traceback" not in done.stderr
    check_same("forests after growth", [7, 7], 15)
    with pytest.raises(RuntimeError, match=r"iteration 15: the ranks hold different forests after growth"):
        check_same("forests after growth", [7, 8], 15)
    assert digest(np.arange(3)) != digest(np.arange(3.0)) and digest(np.arange(3)) == digest(np.arange(3))
