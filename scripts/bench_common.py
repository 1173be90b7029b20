"""Shared header facts for benchmark sections: machine, command, date."""

import os
import platform
import sys
import time


def machine() -> str:
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as fh:
            info = {}
            for ln in fh:
                key, _, value = ln.partition(":")
                info.setdefault(key.strip(), value.strip())
        cpu = info.get("model name", cpu)
        # The VMs this runs on change CPU between sessions, and a virtualised Xeon is named
        # "Intel(R) Xeon(R) Processor" whatever its generation: family, model and the widest
        # vector unit tell two machines apart (timings differ by up to 2x between them).
        if "cpu family" in info and "model" in info:
            vec = next((v for v in ("avx512f", "avx2", "avx") if v in info.get("flags", "").split()), "")
            cpu += f" (family {info['cpu family']} model {info['model']}" + (f", {vec}" if vec else "") + ")"
    except OSError:
        pass
    mem = ""
    try:
        with open("/proc/meminfo") as fh:
            kb = int(fh.readline().split()[1])
        mem = f", {kb / 2**20:.0f} GiB RAM"
    except (OSError, ValueError, IndexError):
        pass
    return f"{cpu}, {os.cpu_count()} cores{mem}, Python {platform.python_version()}"


def header(title: str, command: str) -> str:
    return (
        f"## {title}\n\n- machine: {machine()}\n- command: `{command}`\n"
        f"- date: {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}\n"
    )


def load_average() -> str:
    """The 1, 5 and 15 minute load averages as "a / b / c" ("n/a" where the system has none)."""
    try:
        return " / ".join(f"{x:.1f}" for x in os.getloadavg())
    except OSError:
        return "n/a"


def best_of(fn, repeat=5, warmup=1):
    """Minimum and median wall time (seconds) of fn() over `repeat` runs."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    times.sort()
    return times[0], times[len(times) // 2]


def runs_parser(doc: str):
    """An argument parser for a benchmark over trained runs: --data, --run NAME=RUN (repeated),
    --views, --write and --about."""
    import argparse

    ap = argparse.ArgumentParser(description=doc.splitlines()[0])
    ap.add_argument("--data", required=True)
    ap.add_argument("--run", action="append", required=True, metavar="NAME=RUN")
    ap.add_argument("--views", type=int, default=16)
    ap.add_argument("--write", action="store_true", help="replace the section in docs/BENCHMARKS.md")
    ap.add_argument("--about", default="", help="a sentence on how the runs were trained (goes into the section)")
    return ap


def named_runs(specs, script: str, needs: str) -> dict:
    """{NAME: RUN} from --run NAME=RUN specs, in their order; a spec without "=" or whose RUN
    folder lacks `needs` (a file of a trained run) stops the script, naming it."""
    out = {}
    for spec in specs:
        name, sep, run = spec.partition("=")
        if not sep or not os.path.isfile(os.path.join(run, needs)):
            raise SystemExit(f"{script}: --run wants NAME=RUN with a trained run folder, got {spec!r}")
        out[name] = run
    return out


def replace_section(path: str, name: str, text: str) -> None:
    """Put `text` between the markers of section `name` in the Markdown file at `path`
    (appended with its markers when absent), leaving the rest of the file as it is."""
    start, end = f"<!-- section:{name} -->", f"<!-- /section:{name} -->"
    old = open(path, encoding="utf-8").read() if os.path.exists(path) else ""
    block = f"{start}\n{text.rstrip()}\n{end}"
    if start in old and end in old:
        new = old[: old.index(start)] + block + old[old.index(end) + len(end) :]
    else:
        new = old.rstrip() + "\n\n" + block + "\n"
    tmp = path + ".tmp"
    with open(tmp, "w", encoding="utf-8") as fh:
        fh.write(new)
    os.replace(tmp, path)


if __name__ == "__main__":
    print(machine(), sys.version)
