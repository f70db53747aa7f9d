"""Memory of a long tracking run (issue 16 item 9): RSS before frame 0 and its growth per frame.

    python -m benchmarks.stream_memory --frames 5000 --width 64 --height 48

Writes a sequence of one camera's masks (a moving block, OpenCV, no torchpf.synth), tracks it with a cheap
stand-in likelihood that builds the silhouette cues' per-frame caches (blurred masks, the dual cue's
foreground samples), SIR with 8 particles, human.urdf, and samples the process RSS (/proc, Linux) every
250 frames from inside the likelihood. Prints the RSS added between reading the directory and frame 0, and
the least-squares slope from frame 1000 on (KiB per frame).
"""

from __future__ import annotations

import argparse
import os
import tempfile

import numpy as np
import torch
from torch import nn


def _rss_kib() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 1024


class CacheTouchingLikelihood(nn.Module):
    """log-likelihood ``-|x[:2] - c|^2`` (N,), ``c`` from the foreground samples of the frame's masks: cheap,
    but it fills the per-frame caches of the silhouette cues. With ``samples`` (a list) it appends
    ``(call, RSS KiB)`` every 250 calls."""

    def __init__(self, samples: list | None = None):
        super().__init__()
        self.samples, self.calls = samples, 0

    def forward(self, x, obs):
        if self.samples is not None and self.calls % 250 == 0:
            self.samples.append((self.calls, _rss_kib()))
        self.calls += 1
        sil = obs.silhouettes
        sil.blurred(1.5)
        pts, ok = sil.foreground_samples(64)
        c = pts[ok].mean((0, 1)).to(x) / 100 if bool(ok.any()) else x.new_zeros(2)
        return -((x[..., :2] - c) ** 2).sum(-1)


def main(argv=None) -> int:
    import cv2

    from torchpf import Skeleton
    from torchpf.assets import path
    from torchpf.camera import camera_ring, save_cameras
    from torchpf.proposals import GaussianRandomWalk
    from torchpf.sequence import read_sequence
    from torchpf.tracker import Tracker

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=5000)
    ap.add_argument("--width", type=int, default=64)
    ap.add_argument("--height", type=int, default=48)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    T, W, H = args.frames, args.width, args.height
    with tempfile.TemporaryDirectory() as root:
        rig = camera_ring(1, width=W, height_px=H)
        save_cameras(os.path.join(root, "cameras.yaml"), rig)
        os.makedirs(os.path.join(root, "masks", "cam0"))
        for t in range(T):
            m = np.zeros((H, W), np.uint8)
            x = W // 6 + t % (W // 2)
            m[H // 6 : 5 * H // 6, x : x + W // 5] = 255
            cv2.imwrite(os.path.join(root, "masks", "cam0", f"{t:06d}.png"), m)
        skel = Skeleton.from_urdf(path("human.urdf"))
        D = len(skel.dof_names)
        samples: list = []
        before = _rss_kib()
        seq = read_sequence(root)
        tracker = Tracker(
            skel,
            seq.cameras,
            likelihood=CacheTouchingLikelihood(samples),
            dynamics=GaussianRandomWalk(torch.full((D,), 0.01)),
            filter="sir",
            n_particles=8,
            progress=False,
        )
        tracker.track(seq, init=torch.zeros(D, dtype=torch.float64))
    t, rss = np.array([s for s in samples if s[0] >= min(1000, T // 5)], dtype=np.float64).T
    growth = np.polyfit(t, rss, 1)[0]
    first = (samples[0][1] - before) / 1024
    print(
        f"{T} frames of {W}x{H} masks: RSS at frame 0 - before reading: {first:.1f} MiB; "
        f"growth {growth:.2f} KiB/frame; RSS at the end {samples[-1][1] / 1024:.0f} MiB"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
