"""A small synthetic sequence directory for the command-line and sequence tests (the ``seq_dir`` fixtures)."""


def write_wave_sequence(root, frames: int):
    """``frames`` frames of the generator's wave on human.urdf, two 64x48 cameras, truth.csv at 15 fps,
    written as a sequence directory at ``root``; returns ``root``."""
    from torchpf import Skeleton
    from torchpf.assets import path
    from torchpf.camera import camera_ring
    from torchpf.sequence import write_sequence
    from torchpf.synth import synthesize
    from training.synthetic import generate

    skel = Skeleton.from_urdf(path("human.urdf"))
    angles = generate("wave", frames, 15.0, seed=2).angles
    cams = camera_ring(2, radius=4.0, width=64, height_px=48, target=(0.0, 0.0, 1.0))
    write_sequence(root, synthesize(skel, angles, cams, fps=15.0))
    return root
