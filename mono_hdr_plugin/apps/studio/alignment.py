"""Put a reconstruction next to the truth: the similarity between structure-from-motion's frame and the
studio's, and the studio's cameras moved into the reconstruction (to render held-out views there)."""

from dataclasses import replace

import numpy as np
import torch

from mono_hdr_plugin.core.cameras import Camera


def similarity(source: np.ndarray, target: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """(scale, rotation [3, 3], translation [3]) that best maps points [N, 3] onto `target` (Umeyama 1991)."""
    source_mean, target_mean = source.mean(0), target.mean(0)
    centred_source, centred_target = source - source_mean, target - target_mean
    u, singular, vt = np.linalg.svd(centred_target.T @ centred_source / len(source))
    sign = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:  # a reflection is not a rotation
        sign[2, 2] = -1
    rotation = u @ sign @ vt
    scale = (singular * np.diag(sign)).sum() / (centred_source**2).sum(1).mean()
    return scale, rotation, target_mean - scale * rotation @ source_mean


def camera_into(true_camera: Camera, transform: tuple[float, np.ndarray, np.ndarray], intrinsics: Camera) -> Camera:
    """The studio camera `true_camera` in the reconstruction's frame, with the reconstruction's
    intrinsics (`intrinsics`: any of its cameras), where `transform` maps reconstruction -> studio."""
    scale, rotation, translation = transform
    c2w = true_camera.c2w.double().numpy()
    pose = np.eye(4)
    pose[:3, :3] = rotation.T @ c2w[:3, :3]
    pose[:3, 3] = rotation.T @ (c2w[:3, 3] - translation) / scale
    return replace(intrinsics, c2w=torch.from_numpy(pose).float(), pixels=None)
