"""The training loss reaches the parameters it should, with the weights the config gives.

One real `Trainer.train_step` per case. A copy of the pipeline taken before the step
recomputes the loss from the paper's definitions, written out here from the components
(backbone features, converters, compositing): L = L_ldr + alpha L_hdr + beta L_h2l, with
L_hdr on mu-law(HDR / max) and L_h2l = H2L(mu-law(HDR render / max)) against the LDR photo;
the baselines' LDR is CRF(ln E + ln dt) per primitive and their HDR composites exp(ln E).
Then:
- every logged term equals its configured weight times the recomputed term;
- the gradient the optimiser received equals the gradient of the recomputed total, for every
  parameter (a detached term, a term summed twice or a missing one changes it);
- which parts of the model received gradient at all is stated by hand per case.
"""

import copy
import math

import pytest
import register_backbone  # examples/, put on sys.path by conftest
import torch
from helpers import quiet_config

from backbones.gs import GaussianConfig
from backbones.nerf import MlpFieldConfig, NerfConfig
from mono_hdr_plugin.core.metrics import ssim
from mono_hdr_plugin.training.trainer import Trainer

BASELINES = ("hdr-gs", "hdr-nerf")
LN_5001 = math.log(5001.0)
BACKBONES = {
    "voxel-grid": lambda: register_backbone.VoxelGridConfig(resolution=12, samples_per_ray=24),
    "gs": lambda: GaussianConfig(random_init_points=300),
    "nerf": lambda: NerfConfig(
        field=MlpFieldConfig(
            depth=3,
            width=8,
            skip_layer=1,
            xyz_frequencies=3,
            dir_frequencies=2,
            density_activation="softplus",
            coarse_samples=4,
            fine_samples=4,
            rays_per_step=32,
        )
    ),
}
BETA = {"voxel-grid": 0.01, "nerf": 0.01, "gs": 0.05}  # the paper's beta of each backbone's loss


def mu_law(x: torch.Tensor) -> torch.Tensor:
    return torch.log1p(5000.0 * x) / LN_5001


def normalised(hdr: torch.Tensor) -> torch.Tensor:
    """HDR / its max, clamped to [0, 1], mu-law: the paper's normalisation of both HDR images."""
    return mu_law((hdr / hdr.max()).clamp(0, 1))


def photometric(pred: torch.Tensor, target: torch.Tensor, kind: str) -> torch.Tensor:
    if kind == "mse":
        return ((pred - target) ** 2).mean()
    l1 = (pred - target).abs().mean()
    if pred.dim() == 2:  # pixel batches have no SSIM window
        return l1
    return 0.8 * l1 + 0.2 * (1 - ssim(pred, target))


def relative_hdr_error(hdr: torch.Tensor, truth: torch.Tensor, photo: torch.Tensor) -> torch.Tensor:
    """min over c of mean |log(hdr + f) - log(truth + f) - c| over the pixels whose photo channels all lie in
    (0.05, 0.95), f = 1e-4 x the truth's mean there; the minimiser c (a median) held constant."""
    exposed = ((photo > 0.05) & (photo < 0.95)).all(-1)
    floor = 1e-4 * truth[exposed].mean()
    log_ratio = torch.log(hdr[exposed] + floor) - torch.log(truth[exposed] + floor)
    return (log_ratio - torch.quantile(log_ratio.detach().flatten().double(), 0.5).to(log_ratio.dtype)).abs().mean()


def reference_images(method, features, exposure: float):
    """(LDR, HDR, H2L(normalised HDR) or None), written out from the paper, not from method.forward."""
    if method.config.method in BASELINES:
        log_radiance = features.raw_colors.clamp(max=30.0)
        ldr_colors = method.crf(log_radiance + math.log(exposure))
        image = features.composite(torch.cat([ldr_colors, torch.exp(log_radiance)], -1))
        return image[..., :3], image[..., 3:], None
    image = features.composite(torch.cat([features.colors, method.l2h(features.colors)], -1))
    ldr, hdr = image[..., :3], image[..., 3:]
    return ldr, hdr, (method.h2l(normalised(hdr)) if method.h2l is not None else None)


def reference_terms(pipeline, camera, targets, config, kind: str, beta: float) -> dict[str, torch.Tensor]:
    method = pipeline.method
    features = pipeline.backbone.render_ldr_features(camera)
    ldr, hdr, from_hdr = reference_images(method, features, targets.exposure)
    terms = {}
    if config.use_ldr_loss:
        terms["ldr"] = photometric(ldr, targets.ldr, kind)
        for index, auxiliary in enumerate(features.auxiliary):
            terms[f"ldr_aux{index}"] = photometric(
                reference_images(method, auxiliary, targets.exposure)[0], targets.ldr, kind
            )
    if config.use_hdr_loss and targets.hdr is not None:
        terms["hdr"] = config.alpha * photometric(normalised(hdr), normalised(targets.hdr), kind)
    if config.use_h2l_loss and from_hdr is not None:
        terms["h2l"] = beta * photometric(from_hdr, targets.ldr, kind)
    if config.hdr_log_weight and targets.hdr is not None:
        terms["hdr_log"] = config.hdr_log_weight * relative_hdr_error(hdr, targets.hdr, targets.ldr)
    if config.hdr_prior_weight and targets.radiance is not None:
        exposed = (targets.ldr > 0.05) & (targets.ldr < 0.95)  # channel by channel
        radiance = targets.radiance[exposed]
        floor = 1e-4 * radiance.mean()
        terms["hdr_prior"] = config.hdr_prior_weight * (
            (torch.log(hdr[exposed] + floor) - torch.log(radiance + floor)).abs().mean()
        )
    if config.method == "hdr-nerf":
        unit = method.crf(torch.zeros(1, 3))
        options = config.options
        terms["unit_exposure"] = options.unit_exposure_weight * ((unit - options.unit_exposure_value) ** 2).mean()
    return terms


class StepProbe:
    """Wraps one trainer: keeps a copy of the pipeline before each step, the batch it trained on,
    the RNG state at its render, and the gradients the optimiser was given."""

    def __init__(self, trainer: Trainer):
        self.trainer = trainer
        self.names = {id(p): name for name, p in trainer.pipeline.named_parameters()}
        batch, forward, step = trainer._batch, trainer.pipeline.forward, trainer.optimizer.step

        def record_batch(view, index):
            self.batch = batch(view, index)
            return self.batch

        def record_forward(camera, exposure, view=None):
            self.rng = torch.get_rng_state()
            return forward(camera, exposure, view=view)

        def record_gradients(*args, **kwargs):
            self.gradients = {
                self.names[id(p)]: p.grad.clone()
                for group in trainer.optimizer.param_groups
                for p in group["params"]
                if p.grad is not None
            }
            return step(*args, **kwargs)

        trainer._batch = record_batch
        trainer.pipeline.forward = record_forward
        trainer.optimizer.step = record_gradients

    def step(self) -> tuple[dict, object, dict[str, torch.Tensor]]:
        """One training step: its record, the pipeline as it was, and the recorded gradients."""
        before = copy.deepcopy(self.trainer.pipeline)
        del before.forward  # the copy must not carry the probe
        record = self.trainer.train_step()
        return record, before, self.gradients


def make_trainer(
    tmp_path,
    scene,
    backbone: str,
    ratio: str = "1:1",
    method: str = "mono",
    options: dict | None = None,
    **method_settings,
) -> Trainer:
    """A trainer of `method` with MethodConfig fields `method_settings` and the method's own `options`."""
    config = quiet_config(BACKBONES[backbone](), tmp_path / "run", method, max_steps=10, hdr_view_ratio=ratio)
    for key, value in method_settings.items():
        setattr(config.hdr, key, value)
    for key, value in (options or {}).items():
        setattr(config.hdr.options, key, value)
    return Trainer(config, backbone, scene)


def check_step(probe: StepProbe, backbone: str) -> tuple[dict, set[str]]:
    """Run one step, compare terms and gradients with the recomputation; return the record and
    which parts of the model received gradient ("backbone", "l2h", "h2l", "crf")."""
    trainer = probe.trainer
    record, before, gradients = probe.step()
    config, method = trainer.method.config, trainer.method
    kind = method.loss_kind
    camera, targets = probe.batch
    torch.set_rng_state(probe.rng)
    beta = BETA[backbone] if config.beta is None else config.beta
    expected = reference_terms(before, camera, targets, config, kind, beta)
    assert {k for k in record if k not in ("loss", "ldr_psnr", "skipped", "bad_tensors")} == set(expected)
    for name, value in expected.items():
        assert record[name] == pytest.approx(value.item(), rel=1e-5, abs=1e-9), name
    total = torch.stack(list(expected.values())).sum()
    assert record["loss"] == pytest.approx(total.item(), rel=1e-5)
    total.backward()
    reached = set()
    for name, parameter in before.named_parameters():
        got = gradients.get(name)
        want = parameter.grad
        if want is None or not want.any():
            assert got is None or not got.any(), f"{name} received gradient the loss does not give it"
            continue
        assert got is not None, f"{name} received no gradient"
        scale = float(want.abs().max())
        torch.testing.assert_close(got, want, rtol=1e-4, atol=1e-4 * scale, msg=f"gradient of {name}")
        reached.add(name.split(".")[0] if name.startswith("backbone") else name.split(".")[1])
    return record, reached


SWITCHES = [
    (ldr, hdr, h2l) for ldr in (True, False) for hdr in (True, False) for h2l in (True, False) if ldr or hdr or h2l
]


class TestEveryLossSwitch:
    @pytest.mark.parametrize("ldr,hdr,h2l", SWITCHES)
    def test_mono(self, tmp_path, voxel_scene, ldr, hdr, h2l):
        trainer = make_trainer(
            tmp_path, voxel_scene, "voxel-grid", use_ldr_loss=ldr, use_hdr_loss=hdr, use_h2l_loss=h2l
        )
        record, reached = check_step(StepProbe(trainer), "voxel-grid")
        assert reached == {"backbone"} | ({"l2h"} if hdr or h2l else set()) | ({"h2l"} if h2l else set())

    @pytest.mark.parametrize("method", ["mlp-l2h", "mlp-h2l", "no-h2l"])
    def test_ablations(self, tmp_path, voxel_scene, method):
        trainer = make_trainer(tmp_path, voxel_scene, "voxel-grid", method=method)
        record, reached = check_step(StepProbe(trainer), "voxel-grid")
        assert reached == {"backbone", "l2h"} | (set() if method == "no-h2l" else {"h2l"})
        assert ("h2l" in record) == (method != "no-h2l")

    @pytest.mark.parametrize("method", BASELINES)
    @pytest.mark.parametrize("ldr,hdr", [(True, True), (True, False), (False, True)])
    def test_baselines(self, tmp_path, voxel_scene, method, ldr, hdr):
        trainer = make_trainer(tmp_path, voxel_scene, "voxel-grid", method=method, use_ldr_loss=ldr, use_hdr_loss=hdr)
        record, reached = check_step(StepProbe(trainer), "voxel-grid")
        # the CRF learns from the LDR loss, and for HDR-NeRF from its unit-exposure loss too
        assert reached == {"backbone"} | ({"crf"} if ldr or method == "hdr-nerf" else set())
        assert "h2l" not in record

    def test_weights_other_than_the_defaults(self, tmp_path, voxel_scene):
        trainer = make_trainer(tmp_path, voxel_scene, "voxel-grid", alpha=0.25, beta=0.7, loss="l1_dssim")
        record, _ = check_step(StepProbe(trainer), "voxel-grid")
        assert trainer.method.beta == 0.7 and trainer.method.loss_kind == "l1_dssim"

    @pytest.mark.parametrize("backbone", ["voxel-grid", "gs"])
    def test_relative_hdr_term(self, tmp_path, voxel_scene, backbone):
        trainer = make_trainer(tmp_path, voxel_scene, backbone, hdr_log_weight=0.3)
        record, reached = check_step(StepProbe(trainer), backbone)
        assert record["hdr_log"] > 0 and reached == {"backbone", "l2h", "h2l"}

    def test_hdr_nerf_unit_exposure_weight(self, tmp_path, voxel_scene):
        trainer = make_trainer(
            tmp_path,
            voxel_scene,
            "voxel-grid",
            method="hdr-nerf",
            options={"unit_exposure_weight": 3.0, "unit_exposure_value": 0.73},
        )
        check_step(StepProbe(trainer), "voxel-grid")


class TestWeightsByFiniteDifferences:
    """The total loss is linear in each weight: its slope in alpha is L_hdr, in beta L_h2l."""

    @pytest.mark.parametrize("weight,term", [("alpha", "hdr"), ("beta", "h2l")])
    def test_slope_is_the_unweighted_term(self, tmp_path, voxel_scene, weight, term):
        losses = {}
        for value in (0.2, 0.45):
            weights = {"alpha": 0.6, "beta": 0.01, weight: value}
            trainer = make_trainer(tmp_path, voxel_scene, "voxel-grid", **weights)
            losses[value] = trainer.train_step()
        slope = (losses[0.45]["loss"] - losses[0.2]["loss"]) / 0.25
        assert slope == pytest.approx(losses[0.2][term] / 0.2, rel=1e-4)
        assert slope > 0
        others = [k for k in losses[0.2] if k not in (term, "loss", "ldr_psnr", "skipped", "bad_tensors")]
        for name in others:  # the other terms do not move
            assert losses[0.45][name] == pytest.approx(losses[0.2][name], rel=1e-6), name


class TestHdrViewRatioRows:
    def test_hdr_only_row_trains_without_ldr_photos(self, tmp_path, voxel_scene):
        trainer = make_trainer(tmp_path, voxel_scene, "voxel-grid", ratio="0:1")
        record, reached = check_step(StepProbe(trainer), "voxel-grid")
        assert set(record) & {"ldr", "h2l", "hdr"} == {"hdr"}
        assert reached == {"backbone", "l2h"}

    @pytest.mark.parametrize("method", ["mono", "hdr-gs"])
    def test_ldr_only_row_has_no_hdr_term(self, tmp_path, voxel_scene, method):
        trainer = make_trainer(tmp_path, voxel_scene, "voxel-grid", ratio="1:0", method=method)
        probe = StepProbe(trainer)
        for _ in range(2):
            record, _ = check_step(probe, "voxel-grid")
            assert "hdr" not in record and probe.batch[1].hdr is None
            assert "hdr_prior" in record and probe.batch[1].radiance is not None  # the photos' own radiance

    def test_two_to_one_row_gives_hdr_to_its_views_only(self, tmp_path, voxel_scene):
        trainer = make_trainer(tmp_path, voxel_scene, "voxel-grid", ratio="2:1")
        probe = StepProbe(trainer)
        seen = set()
        for _ in range(len(voxel_scene.train)):
            record, reached = check_step(probe, "voxel-grid")
            camera = probe.batch[0]
            index = next(i for i, v in enumerate(voxel_scene.train) if v.camera is camera)
            assert ("hdr" in record) == trainer.hdr_views[index]
            assert (probe.batch[1].hdr is not None) == trainer.hdr_views[index]
            seen.add("hdr" in record)
        assert seen == {True, False}
        assert sum(trainer.hdr_views) == 2  # 4 training views, LDR:HDR = 2:1


class TestOtherBackbones:
    @pytest.mark.parametrize(
        "backbone,method", [("gs", "mono"), ("gs", "hdr-gs"), ("nerf", "mono"), ("nerf", "hdr-nerf")]
    )
    def test_one_step(self, tmp_path, voxel_scene, backbone, method):
        trainer = make_trainer(tmp_path, voxel_scene, backbone, method=method)
        record, reached = check_step(StepProbe(trainer), backbone)
        assert "backbone" in reached
        assert reached - {"backbone"} == ({"crf"} if method in BASELINES else {"l2h", "h2l"})
        if backbone == "nerf":
            assert "ldr_aux0" in record  # the coarse network's LDR loss


def test_defaults_are_the_papers():
    """The recipe the README reports: alpha 0.6, beta 0.05 (3DGS loss) or 0.01 (NeRF loss), lambda 0.2,
    converters 1 -> 128 -> ... wide, their learning rate 5e-4; HDR-NeRF's unit exposure 0.5 at weight 0.5
    and a 500-step CRF warm-up."""
    from mono_hdr_plugin.core.backbone import OFFICIAL_CONVERTER_LR
    from mono_hdr_plugin.methods.base import DEFAULT_BETA, MethodConfig
    from mono_hdr_plugin.methods.hdr_nerf import HdrNerfOptions

    config = MethodConfig()
    assert (config.method, config.alpha, config.beta, config.dssim_weight, config.hidden) == (
        "mono",
        0.6,
        None,
        0.2,
        128,
    )
    assert (config.use_ldr_loss, config.use_hdr_loss, config.use_h2l_loss, config.loss) == (True, True, True, "auto")
    assert config.converter_lr is None and OFFICIAL_CONVERTER_LR == 5e-4  # None: the backbone's rate
    options = MethodConfig(method="hdr-nerf").options
    assert type(options) is HdrNerfOptions and options == HdrNerfOptions()
    assert (options.unit_exposure_weight, options.unit_exposure_value, options.crf_warmup_steps) == (0.5, 0.5, 500)
    assert DEFAULT_BETA == {"l1_dssim": 0.05, "mse": 0.01}
