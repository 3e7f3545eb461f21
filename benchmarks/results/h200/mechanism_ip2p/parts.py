"""Run parts of the mechanism study (one (instruction, seed) each) in several processes.

    python parts.py QUEUE.json ROOT FACE_CACHE DEADLINE_EPOCH WORKER -- ABLATION FLAGS...

Each worker claims the next unit of QUEUE.json ([[prompt, seed], ...]) under a file lock
and runs it in-process as ``python -m experiments ablation FLAGS --prompts P --seed-range
s:s+1 --out ROOT/units/P_s`` would (the same parser builds the config), with the cached
face reconstruction copied in, so every unit edits the same reconstruction. A worker
claims no unit it could not finish before DEADLINE (its last unit's time as the guess).
"""

import fcntl
import json
import shutil
import sys
import time
from pathlib import Path


def claim(root: Path, n_units: int) -> int | None:
    with open(root / "queue.lock", "a+") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        counter = root / "next"
        i = int(counter.read_text()) if counter.exists() else 0
        if i >= n_units:
            return None
        counter.write_text(str(i + 1))
        return i


def main() -> None:
    queue_file, root, cache, deadline, worker = sys.argv[1:6]
    flags = sys.argv[sys.argv.index("--") + 1:]
    root, cache, deadline = Path(root), Path(cache), float(deadline)
    units = json.loads(Path(queue_file).read_text())
    from experiments.cli import parse
    from jaxedit_lab.ablation import run_ablation
    from experiments.ablation import run_config, seed_range

    last = 0.0
    while time.time() + last < deadline:
        i = claim(root, len(units))
        if i is None:
            break
        prompt, seed = units[i]
        out = root / "units" / f"{prompt.replace(' ', '_')}_{seed}"
        out.mkdir(parents=True, exist_ok=True)
        if not (out / "face").exists():
            shutil.copytree(cache, out / "face")
        args = parse(["ablation", *flags, "--prompts", prompt, "--seed-range",
                      f"{seed}:{seed + 1}", "--out", str(out)])
        config = run_config(args)
        t0 = time.time()
        print(f"[w{worker}] unit {i}: {prompt!r} seed {seed}", flush=True)
        run_ablation(out, config, recon_seed=args.seed, report=False,
                     seeds=seed_range(args.seed_range, config.seeds),
                     log=lambda m: print(f"[w{worker}] {m}", flush=True))
        last = time.time() - t0
        print(f"[w{worker}] unit {i} done in {time.time() - t0:.0f} s", flush=True)


if __name__ == "__main__":
    main()
