"""Standard 3DGS PLY files (the layout common splat viewers read), written atomically."""

from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from backbones.gs.sh import num_sh_bases
from mono_hdr_plugin.data.io import read_ply_vertices, write_ply_vertices


def _attribute_names(rest_bases: int) -> list[str]:
    return (
        ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
        + [f"f_rest_{i}" for i in range(3 * rest_bases)]
        + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    )


def export_ply(backbone, path: str | Path) -> Path:
    """Write the Gaussians of `backbone` (a GaussianBackbone) as a 3DGS PLY at `path`.

    Stored as 3DGS does: opacity as a logit, scales as logs, rotations as (w, x, y, z)
    quaternions, f_rest channel-major. The file appears complete or not at all.
    """
    means = backbone.means.detach().float()
    n = means.shape[0]
    sh_rest = backbone.sh_rest.detach().float()
    columns = [
        means.numpy(),
        np.zeros((n, 3), np.float32),
        backbone.sh_dc.detach().float().reshape(n, 3).numpy(),
        sh_rest.transpose(1, 2).reshape(n, -1).numpy(),
        backbone.opacity_logits.detach().float().reshape(n, 1).numpy(),
        backbone.log_scales.detach().float().numpy(),
        backbone.quats.detach().float().numpy(),
    ]
    data = np.concatenate(columns, axis=1).astype(np.float32)
    names = _attribute_names(sh_rest.shape[1])
    vertices = np.empty(n, dtype=[(name, "f4") for name in names])
    for i, name in enumerate(names):
        vertices[name] = data[:, i]
    return write_ply_vertices(path, vertices)


def load_ply(path: str | Path) -> dict[str, Tensor]:
    """Read a 3DGS PLY: means [N,3], sh_dc [N,1,3], sh_rest [N,K-1,3], log_scales [N,3],
    quats [N,4], opacity_logits [N] (the raw stored values; pass to load_gaussians)."""
    path = Path(path)
    vertex = read_ply_vertices(path, "Gaussian splat")
    names = set(vertex.data.dtype.names)
    required = {"x", "y", "z", "f_dc_0", "opacity", "scale_0", "rot_0"}
    if not required <= names:
        raise ValueError(
            f"{path} lacks 3DGS attributes {sorted(required - names)}: "
            "is it a point cloud rather than a Gaussian splat file?"
        )

    def stack(columns: list[str]) -> Tensor:
        return torch.from_numpy(np.stack([np.asarray(vertex[c], dtype=np.float32) for c in columns], -1))

    rest = sorted((c for c in names if c.startswith("f_rest_")), key=lambda c: int(c.split("_")[-1]))
    rest_bases = len(rest) // 3
    if len(rest) % 3 or (rest_bases + 1) not in [num_sh_bases(d) for d in range(4)]:
        raise ValueError(f"{path} has {len(rest)} f_rest attributes; expected 0, 9, 24 or 45")
    n = len(vertex.data)
    sh_rest = stack(rest).reshape(n, 3, rest_bases).transpose(1, 2) if rest else torch.zeros(n, 0, 3)
    return {
        "means": stack(["x", "y", "z"]),
        "sh_dc": stack(["f_dc_0", "f_dc_1", "f_dc_2"])[:, None, :],
        "sh_rest": sh_rest.contiguous(),
        "log_scales": stack(["scale_0", "scale_1", "scale_2"]),
        "quats": stack(["rot_0", "rot_1", "rot_2", "rot_3"]),
        "opacity_logits": stack(["opacity"])[:, 0],
    }
