"""White balance per view: three gains per training view, applied in linear space with the exposure.

A camera on auto white balance scales its three channels by its own guess of the light, photo by
photo. View i's photo is then LDR_i = f(exp(b_i) g_i ⊙ f^-1(LDR)): b_i its log exposure
(core.exposure), g_i its gains, f the camera response, LDR Mono-HDR's canonical image (for the
methods that take exposure, the gains scale the exposure per channel: CRF(ln E + ln t_i + ln g_i)).

The gains have two gauges, both fixed by construction rather than left to drift:
- brightness: a common factor on the three gains is an exposure change, so each view's log gains
  have zero mean over the channels (the gains change colour only; brightness is b_i's);
- colour: a common colour cast on every view could move into the scene itself, so the log gains
  have zero mean over the training views. The canonical image, and so the HDR, keeps the mean
  balance of the photos: the scene's colour as the capture saw it on average, not one photo's.
A weak L2 pull (`--white-balance-pull`) keeps each view near that mean where its photo does not
say otherwise (a view that sees little of the scene).

EXIF carries no gains to start from: it records WhiteBalance auto (0) or manual (1) and at most a
LightSource class, and the gains themselves sit in maker notes no reader here decodes. Every
view starts at gains 1; EXIF's WhiteBalance tag decides whether they are learned (`--learn-white-
balance auto`, core.exposure.build_view_exposures).
"""

import torch
from torch import Tensor, nn


class ViewWhiteBalance(nn.Module):
    """Per training view: three log gains, learned from 0, with zero mean over channels and views.

    correction: one [3] tensor per view; pull_weight: the L2 pull toward the mean balance; names: the views' file names.
    """

    def __init__(self, views: int, learning_rate: float, pull_weight: float, names: list[str] | None = None):
        super().__init__()
        self.correction = nn.ParameterList(nn.Parameter(torch.zeros(3)) for _ in range(views))
        self.lr = learning_rate
        self.pull_weight = pull_weight
        self.names = names or [str(i) for i in range(views)]

    @classmethod
    def from_state_dict(cls, state: dict[str, Tensor], prefix: str) -> "ViewWhiteBalance | None":
        """An empty module shaped like the one saved under `prefix` (None when there is none)."""
        views = sum(1 for key in state if key.startswith(f"{prefix}correction."))
        return cls(views, 0.0, 0.0) if views else None

    def log_gains(self, view: int | None) -> Tensor:
        """[3] the log gains of training view `view`; zeros (the mean balance) for any other view."""
        if view is None:
            return torch.zeros(3, device=self.correction[0].device)
        # The gauge as a projection, with its gradient: what every view would gain alike (a cast the
        # scene can carry) reaches no view, so it neither drifts nor swamps Adam's step size.
        value = self.correction[view] - torch.stack(list(self.correction)).mean(0)
        return value - value.mean()

    def gains(self) -> Tensor:
        """[V, 3] every training view's gains, as the model now sees them."""
        with torch.no_grad():
            return torch.exp(torch.stack([self.log_gains(view) for view in range(len(self.correction))]))

    def regularisation(self) -> dict[str, Tensor]:
        """The pull toward the mean balance: weight x mean over views of |log g_i|^2."""
        if self.pull_weight == 0:
            return {}
        logs = torch.stack([self.log_gains(view) for view in range(len(self.correction))])
        return {"white_balance_pull": self.pull_weight * (logs**2).sum(-1).mean()}

    def parameter_groups(self) -> list[dict]:
        return [{"name": "white_balance", "params": list(self.correction), "lr": self.lr}]

    def report(self) -> dict:
        """The gains in OUT/learned_exposures.json: per view [r, g, b], with the gauge they are in."""
        return {
            "gauge": "log gains zero mean over the channels of each view and over the training views",
            "start": "gains 1 (EXIF records the white balance mode, not its gains)",
            "pull_weight": self.pull_weight,
            "views": dict(zip(self.names, self.gains().tolist())),
        }


def split_log_scales(log_scales: Tensor) -> tuple[Tensor, Tensor]:
    """Per-channel log scales [3] -> (log exposure, [3] gains with zero log mean): the same light as
    one brightness and a colour, in the gauge of `ViewWhiteBalance`."""
    log_exposure = log_scales.mean()
    return log_exposure, torch.exp(log_scales - log_exposure)
