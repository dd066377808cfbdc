"""The paper's figures (docs/method.md) and the variants, the rows of a table that reproduce them."""

from dataclasses import dataclass

from mono_hdr_plugin.apps.bench.runs import RunSpec

# The paper's figures (docs/method.md), HDR PSNR in dB, by the paper's backbone rows; a registered
# backbone reproduces a row through its `paper_backbone`. The ablations are the paper's 3DGS ones.
PAPER_BASELINE = {"NeRF": "hdr-nerf", "3DGS": "hdr-gs"}
PAPER_TABLE1 = {
    ("NeRF", "hdr-nerf"): 13.76,
    ("NeRF", "mono"): 32.86,
    ("3DGS", "hdr-gs"): 35.30,
    ("3DGS", "mono"): 38.57,
}
PAPER_TABLE1_LDR = {
    ("NeRF", "hdr-nerf"): 30.62,
    ("NeRF", "mono"): 38.78,
    ("3DGS", "hdr-gs"): 39.48,
    ("3DGS", "mono"): 41.68,
}
PAPER_CONVERTERS = {"mlp-l2h": 19.02, "mlp-h2l": 38.43, "no-h2l": 38.19, "mono": 38.57}
LOSS_ROWS = {  # name -> (L_ldr, L_hdr, L_h2l), paper figure (None: "fails to train", no figure)
    "ldr": ((True, False, False), None),
    "hdr": ((False, True, False), 33.93),
    "h2l": ((False, False, True), 11.87),
    "ldr+hdr": ((True, True, False), 38.19),
    "ldr+h2l": ((True, False, True), 13.50),
    "hdr+h2l": ((False, True, True), 33.58),
    "ldr+hdr+h2l": ((True, True, True), 38.57),
}
PAPER_RATIOS = {
    "mono": {"1:1": 38.57, "2:1": 37.97, "3:1": 37.53, "5:1": 35.51, "0:1": 33.93, "1:0": 13.50},
    "hdr-gs": {"1:1": 35.30, "2:1": 35.26, "3:1": 35.16, "5:1": 34.89, "0:1": 33.46, "1:0": 10.51},
}


@dataclass(frozen=True)
class Variant:
    """One row of a table: what is trained (without scene, exposure and seed) and the paper's figure."""

    table: str
    name: str
    spec: RunSpec
    paper_hdr_psnr: float | None = None
    paper_ldr_psnr: float | None = None
    seeds: tuple[int, ...] = (0,)
    scenes: tuple[str, ...] = ()

    def runs(self, exposures: tuple[int, ...]) -> list[RunSpec]:
        return [
            RunSpec(**{**self.spec.__dict__, "scene": scene, "exposure_index": exposure, "seed": seed})
            for scene in self.scenes
            for exposure in exposures
            for seed in self.seeds
        ]
