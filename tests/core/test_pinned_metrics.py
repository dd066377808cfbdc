"""The pipeline refactor changed no behaviour: 200-step runs give the metrics they gave before.

The figures below were produced by commit 27fdab5, before the Pipeline / one-training-loop
refactor, with exactly this configuration (`seed=3`, 2 torch threads); the two 3DGS entries were
re-pinned after the 3DGS CPU work changed the kernel's summation order and the optimiser (see
that commit's message). A change that alters
training on purpose (a new kernel's summation order, a new default) updates them in its own
commit, saying why; a refactor never does. The NeRF entries come from the cpu field of issue 14
(C++ grid kernel, occupancy-grid marching), which replaced the old fast field: same command, seed 3.
"""

import pytest
import register_backbone
import torch
from helpers import quiet_config

from backbones.gs import GaussianConfig
from backbones.nerf import GridFieldConfig, NerfConfig
from mono_hdr_plugin.training.trainer import Trainer

CONFIGS = {
    "gs": lambda: GaussianConfig(random_init_points=400),
    "nerf": lambda: NerfConfig(
        field=GridFieldConfig(
            levels=2,
            min_resolution=4,
            max_resolution=8,
            hidden_width=16,
            min_step=0.125,
            max_samples_per_ray=16,
            occupancy_resolution=8,
            rays_per_step=64,
            samples_per_step=512,
        )
    ),
    "voxel-grid": lambda: register_backbone.VoxelGridConfig(resolution=12, samples_per_ray=24),
}
PINNED = {  # (backbone, method): (HDR PSNR, LDR PSNR) after 200 steps
    # issue 44: L2H-CC made non-decreasing (its weights signed per hidden unit) re-pinned the three mono entries;
    # before it: gs (17.696898545344816, 29.30086301222827), nerf (17.170267501288954, 21.214291641919807),
    # voxel-grid (6.39259982832475, 13.683458474902375)
    ("gs", "mono"): (18.942183106501737, 30.189825242958786),
    ("gs", "hdr-gs"): (14.43623712211377, 24.10180978003195),  # re-pinned by the 3DGS CPU work (issue 13)
    # issue 31: every HDR pixel batch holds the view's brightest pixel (training/batches.py), which changes
    # the rays of every NeRF step; before it: mono (18.37503296016325, 20.533849949479773), hdr-gs
    # (14.504810224973184, 24.01934360748499)
    ("nerf", "mono"): (19.442031099853942, 22.22576122096218),
    ("nerf", "hdr-gs"): (14.435226942036174, 24.94266602800078),
    ("voxel-grid", "mono"): (5.747238184534223, 13.58577042142814),
    ("voxel-grid", "hdr-gs"): (21.072537882487474, 22.749774258012295),
}


@pytest.mark.slow
@pytest.mark.parametrize("backbone,method", sorted(PINNED))
def test_200_steps_reproduce_the_pinned_metrics(tmp_path, backbone, method):
    assert torch.get_num_threads() == 2  # tests/conftest.py: the pinned runs used 2 threads
    scene = register_backbone.make_capture(size=16, views=8)
    backbone_config = CONFIGS[backbone]()
    config = quiet_config(backbone_config, tmp_path / "run", method, max_steps=200, seed=3)
    metrics = Trainer(config, backbone, scene).train()
    # The C++/OpenMP kernels of gs and nerf sum in an order that can differ between machines and with the
    # machine's load, even on MKL's AVX2 path (tests/conftest.py): on 2026-12-03, with other work running,
    # gs/mono ended 9.2e-5 and nerf/hdr-gs 2.6e-6 of a PSNR from their pins; on 2026-12-06, on an AMD EPYC
    # machine, quiet, gs/mono's LDR ended 1.0e-3 from it (30.1593), the same on the tree that set the pin.
    # Fixed-order sums (issue 48) will bring this back to 1e-6. The voxel grid is plain torch.
    tolerance = {"voxel-grid": 1e-6, "gs": 2e-3}.get(backbone, 2e-4)
    assert (metrics["hdr_psnr"], metrics["ldr_psnr"]) == pytest.approx(PINNED[(backbone, method)], rel=tolerance)
