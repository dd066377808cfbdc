"""VisibleRowAdam (training.visible_adam): Adam on the rows a step saw.

References: torch.optim.Adam where every row is seen, and Adam written out in float64 numpy (Kingma &
Ba, algorithm 1, with one step count per parameter) where rows are left out."""

import numpy as np
import pytest
import torch

from mono_hdr_plugin.training.visible_adam import VisibleRowAdam

BETAS, EPS, LR = (0.9, 0.999), 1e-8, 0.05


def numpy_adam(values, gradients, rows_per_step):
    """Rows [N, C] after one step per gradient, each stepping only its rows: the rows left out keep
    their values and moments; the step count (bias correction) counts every step."""
    param = values.astype(np.float64).copy()
    first, second = np.zeros_like(param), np.zeros_like(param)
    for step, (grad, rows) in enumerate(zip(gradients, rows_per_step, strict=True), start=1):
        grad = grad.astype(np.float64)
        first[rows] = BETAS[0] * first[rows] + (1 - BETAS[0]) * grad[rows]
        second[rows] = BETAS[1] * second[rows] + (1 - BETAS[1]) * grad[rows] ** 2
        corrected_first = first[rows] / (1 - BETAS[0] ** step)
        corrected_second = second[rows] / (1 - BETAS[1] ** step)
        param[rows] -= LR * corrected_first / (np.sqrt(corrected_second) + EPS)
    return param, first, second


def run(rows_per_step, fused: bool, seed: int = 0):
    """A per-row parameter and a plain one, stepped with random gradients; returns both and the optimiser."""
    generator = torch.Generator().manual_seed(seed)
    rows_param = torch.nn.Parameter(torch.randn(7, 3, generator=generator))
    plain_param = torch.nn.Parameter(torch.randn(4, generator=generator))
    start = (rows_param.detach().clone(), plain_param.detach().clone())
    groups = [{"params": [rows_param], "per_row": True}, {"params": [plain_param]}]
    optimizer = VisibleRowAdam(groups, lr=LR, betas=BETAS, eps=EPS, fused=fused)
    gradients = []
    for rows in rows_per_step:
        gradients.append((torch.randn(7, 3, generator=generator), torch.randn(4, generator=generator)))
        rows_param.grad, plain_param.grad = (g.clone() for g in gradients[-1])
        optimizer.step(rows)
    return rows_param, plain_param, start, gradients, optimizer


class TestVisibleRowAdam:
    @pytest.mark.parametrize("fused", [False, True])
    def test_every_row_seen_is_torch_adam(self, fused):
        every = torch.arange(7)
        rows_param, plain_param, start, gradients, _ = run([every, None, every], fused)
        reference = [torch.nn.Parameter(tensor.clone()) for tensor in start]
        adam = torch.optim.Adam(reference, lr=LR, betas=BETAS, eps=EPS)
        for grads in gradients:
            for param, grad in zip(reference, grads, strict=True):
                param.grad = grad.clone()
            adam.step()
        torch.testing.assert_close(rows_param.detach(), reference[0].detach(), rtol=1e-6, atol=1e-7)
        torch.testing.assert_close(plain_param.detach(), reference[1].detach(), rtol=1e-6, atol=1e-7)

    @pytest.mark.parametrize("fused", [False, True])
    def test_rows_left_out_keep_values_and_moments(self, fused):
        rows_per_step = [torch.tensor([0, 2, 5]), torch.tensor([1, 2]), torch.tensor([2, 3, 6]), torch.tensor([0])]
        rows_param, plain_param, start, gradients, optimizer = run(rows_per_step, fused)
        expected, first, second = numpy_adam(
            start[0].numpy(), [g[0].numpy() for g in gradients], [r.numpy() for r in rows_per_step]
        )
        np.testing.assert_allclose(rows_param.detach().numpy(), expected, rtol=1e-5, atol=1e-6)
        state = optimizer.state[rows_param]
        np.testing.assert_allclose(state["exp_avg"].numpy(), first, rtol=1e-5, atol=1e-7)
        np.testing.assert_allclose(state["exp_avg_sq"].numpy(), second, rtol=1e-5, atol=1e-9)
        assert float(state["step"]) == 4
        assert torch.equal(rows_param.detach()[4], start[0][4])  # never seen: untouched
        assert (state["exp_avg"][4] == 0).all()
        plain_expected, _, _ = numpy_adam(start[1].numpy(), [g[1].numpy() for g in gradients], [slice(None)] * 4)
        np.testing.assert_allclose(plain_param.detach().numpy(), plain_expected, rtol=1e-5, atol=1e-6)

    def test_state_dict_round_trip_keeps_adams_keys_and_the_flag(self):
        rows_param, _, _, _, optimizer = run([torch.tensor([1, 3])], fused=True)
        assert set(optimizer.state[rows_param]) == {"step", "exp_avg", "exp_avg_sq"}
        saved = optimizer.state_dict()
        fresh = VisibleRowAdam([{"params": [rows_param], "per_row": True}, {"params": [torch.zeros(4)]}], lr=LR)
        fresh.load_state_dict(saved)
        assert fresh.param_groups[0]["per_row"] and not fresh.param_groups[1].get("per_row")
        torch.testing.assert_close(fresh.state[rows_param]["exp_avg"], optimizer.state[rows_param]["exp_avg"])

    def test_weight_decay_is_refused(self):
        param = torch.nn.Parameter(torch.ones(3, 2))
        optimizer = VisibleRowAdam([{"params": [param], "per_row": True}], lr=LR, weight_decay=0.1)
        param.grad = torch.ones(3, 2)
        with pytest.raises(ValueError, match="weight decay"):
            optimizer.step(torch.tensor([0]))
