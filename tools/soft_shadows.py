"""Soft shadows against Cycles: a scene's (soft_room's) Diffuse Direct, ours (the batch CLI) and
Cycles' (a cached reference).

    python -m tools.soft_shadows [--scene soft_room] [--samples 1024] [--resolution 128]
        [--before REV] [--set KEY=VALUE ...]

prints, over the pixels Cycles lights above 0.02: our mean Diffuse Direct over Cycles', the
fraction of them we light with less than a tenth of Cycles' (holes and spikes at shadow
edges, issue 17) and the relative RMSE. ``--before REV`` also renders with the code of that
git revision (extracted with git archive into a temporary folder) for a before/after line.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
CACHE = ROOT / ".cache" / "soft_shadows"
LIT = 0.02  # the threshold: pixels Cycles lights above it


def render_ours(blend: Path, out: Path, res: int, code: Path = ROOT,
                sets: tuple[str, ...] = ()) -> dict:
    """Our frame of ``blend`` by the batch CLI of the code in ``code`` (``sets``: its --set
    KEY=VALUE overrides)."""
    from lpv_core.render import exr

    env = dict(os.environ, PYTHONPATH=str(code))
    cmd = [sys.executable, "-m", "lpv_addon.batch", str(blend), "--out", str(out), "--frames",
           "1", "--resolution", f"{res}x{res}", "--quiet",
           *(a for kv in sets for a in ("--set", kv))]
    proc = subprocess.run(cmd, cwd=code, env=env, capture_output=True, text=True, check=False)
    if proc.returncode != 0:
        raise RuntimeError(proc.stderr[-2000:])
    return exr.read_multilayer(out / "0001.exr")


def direct_figures(ours: dict, ref: dict) -> dict:
    """Mean ratio, hole fraction and relative RMSE of Diffuse Direct over Cycles' lit pixels."""
    from lpv_core.render import error

    a = ours["Diffuse Direct"][..., :3].mean(-1)
    b = ref["Diffuse Direct"][..., :3].mean(-1)
    lit = b > LIT
    return {"lit_pixels": int(lit.sum()), "mean_ratio": float(a[lit].mean() / b[lit].mean()),
            "holes": float((a[lit] < 0.1 * b[lit]).mean()),
            "rmse": float(error.relative_rmse(ours["Diffuse Direct"][..., :3],
                                              ref["Diffuse Direct"][..., :3]))}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scene", default="soft_room", help="a scene of tools.scenes")
    p.add_argument("--samples", type=int, default=1024)
    p.add_argument("--resolution", type=int, default=128)
    p.add_argument("--before", default=None, help="git revision to compare with")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="a GI setting for our renders (the batch CLI's --set)")
    args = p.parse_args(argv)
    sys.path.insert(0, str(ROOT / "tools"))
    from make_references import ensure_reference

    from lpv_core.render import exr

    res = args.resolution
    blend, ref_path = ensure_reference(args.scene, CACHE, samples=args.samples, bounces=1,
                                       resolution=(res, res))
    ref = exr.read_multilayer(ref_path)
    runs = {"now": ROOT}
    with tempfile.TemporaryDirectory(prefix="lpv_soft_") as tmp:
        if args.before:
            code = Path(tmp) / "before"
            code.mkdir()
            archive = subprocess.run(["git", "archive", args.before], cwd=ROOT,
                                     capture_output=True, check=True).stdout
            subprocess.run(["tar", "-x", "-C", str(code)], input=archive, check=True)
            runs = {f"before ({args.before})": code, **runs}
        for label, code in runs.items():
            out = Path(tmp) / label.split()[0]
            fig = direct_figures(render_ours(blend, out, res, code, tuple(args.set)), ref)
            extra = "".join(f" {kv}" for kv in args.set)
            print(f"{args.scene} {res}x{res}{extra}, Cycles {args.samples} spp, {label}: Diffuse Direct "
                  f"mean ours/Cycles {fig['mean_ratio']:.4f} over {fig['lit_pixels']} pixels "
                  f"Cycles lights above {LIT}; {100 * fig['holes']:.2f} % of them below a "
                  f"tenth of Cycles'; relative RMSE {fig['rmse']:.3f}")
    return 0


if __name__ == "__main__":
    np.seterr(all="ignore")
    sys.exit(main())
