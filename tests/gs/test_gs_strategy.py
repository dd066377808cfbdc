"""Densification strategies: parameters and Adam moments stay aligned, the budget holds, the
MCMC relocation formula, the official clone/split/prune/reset rules."""

import math
from types import SimpleNamespace

import pytest
import torch
from test_gs_backbone import make_optimizer, make_scene, train_step

from backbones.gs import GAUSSIAN_PARAMETERS, DefaultStrategy, GaussianBackbone, GaussianConfig, McmcStrategy
from backbones.gs.strategy import RefineSchedule, relocation


def assert_optimizer_consistent(backbone, optimizer):
    n = backbone.num_gaussians
    for group in optimizer.param_groups:
        (param,) = group["params"]
        assert param is getattr(backbone, group["name"]), f"{group['name']} not the module's parameter"
        assert param.shape[0] == n, group["name"]
        state = optimizer.state.get(param)
        if state:
            assert state["exp_avg"].shape == param.shape and state["exp_avg_sq"].shape == param.shape


def tag_moments(optimizer, n):
    """Write each row's number into its exp_avg, so edits can be traced row by row."""
    for group in optimizer.param_groups:
        param = group["params"][0]
        rows = torch.arange(n, dtype=torch.float32).reshape(-1, *[1] * (param.dim() - 1))
        optimizer.state[param]["exp_avg"] = rows.expand_as(param).clone()


def fake_projection(n: int, grad_rows: slice, width: int, height: int):
    """A projection in which every Gaussian is visible and `grad_rows` have a large screen gradient."""
    means2d = torch.zeros(n, 2, requires_grad=True)
    means2d.grad = torch.zeros(n, 2)
    means2d.grad[grad_rows] = 1.0
    return SimpleNamespace(
        index=torch.arange(n),
        means2d=means2d,
        radii=torch.ones(n, dtype=torch.int32),
        width=width,
        height=height,
        frame=None,  # a whole image (ProjectedGaussians.frame)
    )


class TestRelocationFormula:
    @pytest.mark.parametrize("copies", [1, 2, 3, 7])
    def test_against_the_paper_sum(self, copies):
        """o' = 1 - (1 - o)^(1/N), s' = s o / sum_i sum_k C(i-1,k) (-1)^k o'^(k+1) / sqrt(k+1), summed directly."""
        opacity, scale = 0.63, 0.2
        new_o, new_s = relocation(torch.tensor([opacity]), torch.full((1, 3), scale), torch.tensor([copies]))
        expected_o = 1 - (1 - opacity) ** (1 / copies)
        denominator = sum(
            math.comb(i - 1, k) * (-1) ** k * expected_o ** (k + 1) / math.sqrt(k + 1)
            for i in range(1, copies + 1)
            for k in range(i)
        )
        assert new_o.item() == pytest.approx(expected_o, rel=1e-6)
        torch.testing.assert_close(new_s, torch.full((1, 3), scale * opacity / denominator))

    def test_one_copy_changes_nothing(self):
        o, s = torch.rand(20) * 0.9 + 0.05, torch.rand(20, 3)
        new_o, new_s = relocation(o, s, torch.ones(20, dtype=torch.long))
        torch.testing.assert_close(new_o, o)
        torch.testing.assert_close(new_s, s)

    def test_copies_composite_to_the_original_opacity(self):
        """N copies of opacity o' stacked at the centre let through (1 - o')^N = 1 - o."""
        o = torch.tensor([0.3, 0.9, 0.99])
        for copies in (2, 5, 51):
            new_o, _ = relocation(o, torch.ones(3, 3), torch.full((3,), copies))
            torch.testing.assert_close(1 - (1 - new_o) ** copies, o, rtol=1e-5, atol=1e-6)


class TestMcmcStrategy:
    def _setup(self, budget=350, **strategy):
        scene = make_scene(points=300)
        backbone = GaussianBackbone(GaussianConfig(strategy=McmcStrategy(max_gaussians=budget, **strategy)), scene)
        optimizer = make_optimizer(backbone)
        camera = scene.train_cameras[0]
        target = torch.rand(camera.height, camera.width, 3, generator=torch.Generator().manual_seed(1))
        train_step(backbone, optimizer, camera, target, 0)  # fills Adam's moments
        return backbone, optimizer, camera, target

    def test_relocate_moves_dead_rows_onto_live_ones_with_moments_reset(self):
        backbone, optimizer, _, _ = self._setup()
        n = backbone.num_gaussians
        tag_moments(optimizer, n)
        dead = torch.zeros(n, dtype=torch.bool)
        dead[:40] = True
        with torch.no_grad():
            backbone.opacity_logits[dead] = -10.0
        before = {name: getattr(backbone, name).detach().clone() for name in GAUSSIAN_PARAMETERS}
        moved = backbone.config.strategy.relocate(backbone, optimizer)
        assert moved == 40 and backbone.num_gaussians == n
        assert_optimizer_consistent(backbone, optimizer)
        means = backbone.means.detach()
        sources = [int(((before["means"] - row).abs().sum(-1) == 0).nonzero()[0]) for row in means[:40]]
        assert all(s >= 40 for s in sources), "dead Gaussians land on live ones"
        for source in set(sources):
            torch.testing.assert_close(backbone.opacity_logits[source], backbone.opacity_logits[sources.index(source)])
            assert torch.sigmoid(backbone.opacity_logits[source]) < torch.sigmoid(before["opacity_logits"][source])
        moments = optimizer.state[backbone.means]["exp_avg"][:, 0]
        touched = torch.tensor(sorted(set(sources) | set(range(40))))
        assert moments[touched].abs().max() == 0
        untouched = torch.ones(n, dtype=torch.bool)
        untouched[touched] = False
        torch.testing.assert_close(moments[untouched], torch.arange(n, dtype=torch.float32)[untouched])

    def test_grow_adds_five_percent_up_to_the_budget(self):
        backbone, optimizer, _, _ = self._setup(budget=310)
        n = backbone.num_gaussians
        tag_moments(optimizer, n)
        added = backbone.config.strategy.grow(backbone, optimizer, backbone.budget)
        assert added == 10 and backbone.num_gaussians == 310  # 5 % of 300 would be 15
        assert_optimizer_consistent(backbone, optimizer)
        moments = optimizer.state[backbone.sh_dc]["exp_avg"][:, 0, 0]
        torch.testing.assert_close(moments[:n], torch.arange(n, dtype=torch.float32))
        assert moments[n:].abs().max() == 0
        assert backbone.config.strategy.grow(backbone, optimizer, backbone.budget) == 0

    def test_training_never_exceeds_the_budget(self):
        backbone, optimizer, camera, target = self._setup(
            budget=330, refine_start=0, refine_every=1, min_refine_every=1
        )
        backbone.set_run_length(30_000)
        counts = []
        for step in range(1, 12):
            with torch.no_grad():
                backbone.opacity_logits[step::7] = -12.0  # keep killing some, so relocation has work
            train_step(backbone, optimizer, camera, target, step)
            counts.append(backbone.num_gaussians)
            assert_optimizer_consistent(backbone, optimizer)
        assert counts[0] == 315 and max(counts) == 330 == counts[-1]
        assert torch.isfinite(backbone.means).all()

    def test_noise_moves_only_near_dead_gaussians(self):
        backbone, optimizer, _, _ = self._setup()
        with torch.no_grad():
            backbone.opacity_logits[:10] = -6.0  # opacity 0.0025: gate ~ 0.67
            backbone.opacity_logits[10:] = 2.0  # opacity 0.88: gate ~ 0
        before = backbone.means.detach().clone()
        backbone.config.strategy.add_position_noise(backbone, means_lr=1e-3)
        moved = (backbone.means.detach() - before).norm(dim=-1)
        assert (moved[:10] > 0).all() and (moved[10:] == 0).all()

    def test_regularisers(self):
        backbone, _, _, _ = self._setup(opacity_reg=0.5, scale_reg=0.25)
        terms = backbone.regularisation()
        torch.testing.assert_close(terms["opacity_reg"], 0.5 * torch.sigmoid(backbone.opacity_logits).mean())
        torch.testing.assert_close(terms["scale_reg"], 0.25 * backbone.log_scales.exp().mean())
        assert GaussianBackbone(GaussianConfig(), make_scene()).regularisation() == {}


class TestDefaultStrategy:
    def _trained(self, **strategy):
        scene = make_scene()
        backbone = GaussianBackbone(GaussianConfig(strategy=DefaultStrategy(**strategy)), scene)
        backbone.set_run_length(300)
        optimizer = make_optimizer(backbone)
        camera = scene.train_cameras[0]
        target = torch.rand(camera.height, camera.width, 3, generator=torch.Generator().manual_seed(1))
        return backbone, optimizer, camera, target

    def test_clone_and_split_keep_optimizer_aligned(self):
        backbone, optimizer, camera, target = self._trained(prune_opacity=0.0)
        train_step(backbone, optimizer, camera, target, 0)
        n = backbone.num_gaussians
        tag_moments(optimizer, n)
        with torch.no_grad():
            backbone.log_scales[:4] = -8.0  # small: cloned
            backbone.log_scales[4:8] = -0.5  # large: split
        old_means = backbone.means.detach().clone()
        old_scales = backbone.log_scales.detach().clone()
        strategy = backbone.config.strategy
        state = strategy.initial_state(n)  # forget step 0's real gradients
        schedule = strategy.schedule(backbone.max_steps)
        step = schedule.every * (schedule.start // schedule.every + 1)
        strategy.step_post_backward(
            backbone,
            optimizer,
            state,
            step,
            backbone.max_steps,
            fake_projection(n, slice(0, 8), camera.width, camera.height),
            backbone.budget,
        )

        assert backbone.num_gaussians == n + 4 + 4  # 4 clones, 4 splits into 2
        assert_optimizer_consistent(backbone, optimizer)
        tags = optimizer.state[backbone.means]["exp_avg"][:, 0]
        survivors = [i for i in range(n) if not 4 <= i < 8]
        torch.testing.assert_close(tags[: n - 4], torch.tensor(survivors, dtype=torch.float32))
        torch.testing.assert_close(backbone.means.detach()[: n - 4], old_means[survivors])
        assert tags[n - 4 :].abs().max() == 0, "new rows start with zero moments"
        torch.testing.assert_close(backbone.means.detach()[n - 4 : n], old_means[:4])  # clones
        torch.testing.assert_close(
            backbone.log_scales.detach()[n:], (old_scales[4:8] - torch.log(torch.tensor(1.6))).repeat(2, 1)
        )
        assert state["grad2d_sum"].shape == (n + 8,) and state["grad2d_sum"].abs().max() == 0
        train_step(backbone, optimizer, camera, target, step + 1)  # Adam still steps
        assert torch.isfinite(backbone.means).all()

    def test_growth_stops_at_max_gaussians(self):
        backbone, optimizer, camera, target = self._trained(prune_opacity=0.0, max_gaussians=305)
        train_step(backbone, optimizer, camera, target, 0)
        n = backbone.num_gaussians
        strategy = backbone.config.strategy
        schedule = strategy.schedule(backbone.max_steps)
        step = schedule.every * (schedule.start // schedule.every + 1)
        strategy.step_post_backward(
            backbone,
            optimizer,
            strategy.initial_state(n),
            step,
            backbone.max_steps,
            fake_projection(n, slice(0, 100), camera.width, camera.height),
            backbone.budget,
        )
        assert n == 300 and backbone.num_gaussians == 305
        assert_optimizer_consistent(backbone, optimizer)

    def test_prune_removes_transparent_rows(self):
        backbone, optimizer, camera, target = self._trained(grad_threshold=1e9)
        with torch.no_grad():
            backbone.opacity_logits[:50] = -20.0
        keep_means = backbone.means.detach()[50:].clone()
        schedule = backbone.config.strategy.schedule(backbone.max_steps)
        step = schedule.every * (schedule.start // schedule.every + 1)
        train_step(backbone, optimizer, camera, target, step - 1)
        train_step(backbone, optimizer, camera, target, step)
        assert backbone.num_gaussians == keep_means.shape[0]
        assert_optimizer_consistent(backbone, optimizer)

    def test_never_prunes_to_empty(self):
        backbone, optimizer, camera, target = self._trained(grad_threshold=1e9)
        with torch.no_grad():
            backbone.opacity_logits.fill_(-20.0)
        schedule = backbone.config.strategy.schedule(backbone.max_steps)
        step = schedule.every * (schedule.start // schedule.every + 1)
        train_step(backbone, optimizer, camera, target, step)
        assert backbone.num_gaussians == 1

    def test_opacity_reset_clears_moments(self):
        backbone, optimizer, camera, target = self._trained(grad_threshold=1e9)
        reset = backbone.config.strategy.reset_every(backbone.max_steps)
        train_step(backbone, optimizer, camera, target, reset - 1)
        with torch.no_grad():
            backbone.opacity_logits.fill_(3.0)
        train_step(backbone, optimizer, camera, target, reset)
        assert torch.sigmoid(backbone.opacity_logits).max() <= 0.0100001
        assert optimizer.state[backbone.opacity_logits]["exp_avg"].abs().max() == 0
        assert_optimizer_consistent(backbone, optimizer)

    def test_schedule_scales_with_run_length(self):
        strategy = DefaultStrategy()
        full, short = strategy.schedule(30_000), strategy.schedule(3_000)
        assert (full.start, full.stop, full.every, strategy.reset_every(30_000)) == (500, 15_000, 100, 3000)
        assert (short.start, short.stop, short.every, strategy.reset_every(3_000)) == (50, 1500, 10, 300)


def test_refine_schedule_due():
    schedule = RefineSchedule.scaled(3000, 500, 25_000, 100, 10)
    assert (schedule.start, schedule.stop, schedule.every) == (50, 2500, 10)
    assert [s for s in range(3000) if schedule.due(s)][:2] == [60, 70]
    assert not schedule.due(2500) and schedule.due(2490)
