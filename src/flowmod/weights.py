"""Trained flow-network weights for users who have internet (``make weights``).

    python -m flowmod.weights            # download RAFT's KITTI checkpoints, list what is there
    python -m flowmod.weights --status   # only list what is there

RAFT (large and small) comes through torchvision's own weight API: its URLs, and the hash
that torchvision checks on download, into ``$TORCH_HOME/hub/checkpoints/``, where the flow
stage finds it without any parameter. FastFlowNet has no package: the official checkpoint
(``checkpoints/fastflownet_ft_kitti.pth`` of https://github.com/ltkong218/FastFlowNet, MIT
licence) is copied there by hand; it is verified when loaded (its 104 tensors must match the
architecture's names and shapes, or the error names the file and the keys). Nothing else in
the study ever downloads: without these files the networks refuse to run and say where to
put them. Offline, the download fails with one line saying so.
"""

from __future__ import annotations

import argparse
import sys
import urllib.error
from pathlib import Path

from flowmod.flow import architectures as nets
from flowmod.flow.networks import cache_files
from flowmod.flowweights import CATALOG, WEIGHTS_PARAM

#: The checkpoints downloaded (architecture, torchvision enum member): the catalog's entries
#: with a download, RAFT's KITTI fine-tuned large model (the paper's choice of KITTI weights)
#: and the small model's only published weights.
RAFT_WEIGHTS = tuple((w.torchvision_arch, w.download) for w in CATALOG.values() if w.download)


def status() -> list[tuple[str, str, bool]]:
    """(method, file, present) for every weight file the flow stage looks for."""
    return [(m, str(f), f.is_file()) for m in WEIGHTS_PARAM for f in cache_files(m)]


def available_networks() -> list[str]:
    """The network methods with a weight file in place."""
    return sorted({m for m, _, present in status() if present})


def download() -> list[Path]:
    """Download the RAFT checkpoints of :data:`RAFT_WEIGHTS` with torchvision's hash check;
    :class:`ConnectionError` with one line when there is no network."""
    from torchvision.models import optical_flow as of  # here: ~1 s to import

    enums = {"raft_large": of.Raft_Large_Weights, "raft_small": of.Raft_Small_Weights}
    done = []
    for arch, member in RAFT_WEIGHTS:
        w = enums[arch][member]
        target = nets.hub_checkpoint_dir() / Path(w.url).name
        if not target.is_file():
            try:
                w.get_state_dict(progress=True, check_hash=True)
            except (urllib.error.URLError, OSError) as e:
                raise ConnectionError(
                    f"cannot download {w.url} ({getattr(e, 'reason', e)}): make weights needs "
                    f"internet; elsewhere, copy the file to {target}") from None
        done.append(target)
    return done


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m flowmod.weights",
                                 description=__doc__.split("\n\n")[0])
    ap.add_argument("--status", action="store_true", help="list the weight files; download nothing")
    args = ap.parse_args(argv)
    if not args.status:
        try:
            for path in download():
                print(f"raft weights: {path}")
        except ConnectionError as e:
            print(f"make weights: {e}", file=sys.stderr)
            return 1
    print(f"FastFlowNet: put fastflownet_ft_kitti.pth (checkpoints/ of "
          f"https://github.com/ltkong218/FastFlowNet) into {nets.hub_checkpoint_dir()}/")
    for method, path, present in status():
        print(f"{'present' if present else 'missing':8s} {method:12s} {path}")
    nets_here = available_networks()
    print("network methods usable now: " + (", ".join(nets_here) or "none") +
          " (add them to flow_methods, e.g. SET=\"flow_methods=[dis,farneback,"
          + ",".join(nets_here or ["raft"]) + "]\")")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
