"""``python -m flowmod.world --profile demo``: build (or reuse) the profile's world."""

from __future__ import annotations

import argparse
import sys
import time

from flowmod.params import ProfileError, load_profile, parse_overrides
from flowmod.world.dataset import ensure_world
from flowmod.world.truth import WorldError


def main(argv: list[str] | None = None) -> int:
    """``python -m flowmod.world --profile demo``: build (or reuse) the profile's world."""
    ap = argparse.ArgumentParser(prog="python -m flowmod.world", description=main.__doc__)
    ap.add_argument("--profile", default="demo")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    args = ap.parse_args(argv)
    try:
        p = load_profile(args.profile, **parse_overrides(args.overrides))
        t0 = time.perf_counter()
        root = ensure_world(p)
    except (ProfileError, WorldError) as e:
        print(f"{type(e).__name__}: {e}", file=sys.stderr)
        return 2
    size = sum(f.stat().st_size for f in root.rglob("*") if f.is_file())
    print(f"world: {root / p.version} ({size / 1e6:.0f} MB, {time.perf_counter() - t0:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
