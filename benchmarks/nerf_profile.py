"""Where one NeRF training step's time goes, phase by phase (docs/nerf_profile.md).

    python benchmarks/nerf_profile.py --scene demo --method mono --warmup 60 --steps 40

Trains `warmup` steps (the density grid fills, samples concentrate), then times `steps` more
of the ordinary training step, with wall-clock timers wrapped around its parts:

- sampling: everything the backbone does to place samples (rays, box, marching, occupancy),
  i.e. render_ldr_features minus the field's own calls;
- field: the field's forward calls (encoding, density and colour MLPs);
- l2h / crf: the method's per-sample converter (L2H-CC, or the baselines' CRF);
- composite: the compositing closure (both LDR and HDR channels);
- backward: loss.backward();
- optimiser: optimizer.step();
- density grid: the backbone's after_step (occupancy refreshes);
- other: the rest of the step (loss terms, H2L-CC on pixels, batch assembly, bookkeeping).

Timers wrap the objects of one trainer from the outside, so the step itself runs unchanged.
"""

import functools
import json
import statistics
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import torch

from mono_hdr_plugin.apps.bench import script_args as args_of
from mono_hdr_plugin.apps.bench.runs import RunBudget, RunSpec, build_run, cached_scene

PHASES = ("sampling", "field", "l2h/crf", "composite", "backward", "optimiser", "density grid", "other")


class PhaseClock:
    """Accumulates wall-clock seconds per phase; nested timers subtract from their parent."""

    def __init__(self):
        self.seconds: dict[str, float] = defaultdict(float)
        self._stack: list[list] = []

    def wrap(self, phase: str, function):
        @functools.wraps(function)
        def timed(*args, **kwargs):
            self._stack.append([phase, time.perf_counter(), 0.0])
            try:
                return function(*args, **kwargs)
            finally:
                name, started, inner = self._stack.pop()
                elapsed = time.perf_counter() - started
                self.seconds[name] += elapsed - inner
                if self._stack:
                    self._stack[-1][2] += elapsed

        return timed


def field_functions(backbone) -> list[tuple[object, str]]:
    """(object, attribute) of every field forward the backbone calls, whichever field it has."""
    found = []
    for module_name in ("grid_field", "coarse_field", "fine_field", "field"):
        module = getattr(backbone, module_name, None)
        if module is None:
            continue
        for name in ("density_and_geometry", "color", "forward"):
            if name in vars(type(module)):
                found.append((module, name))
    return found


def instrument(trainer, clock: PhaseClock) -> None:
    backbone, method = trainer.backbone, trainer.method
    for module, name in field_functions(backbone):
        setattr(module, name, clock.wrap("field", getattr(module, name)))
    for converter in ("l2h", "crf"):
        if hasattr(method, converter):
            module = getattr(method, converter)
            module.forward = clock.wrap("l2h/crf", module.forward)
    render = backbone.render_ldr_features

    def render_and_wrap(camera):
        features = render(camera)
        features.composite = clock.wrap("composite", features.composite)
        for aux in features.auxiliary:
            aux.composite = clock.wrap("composite", aux.composite)
        return features

    backbone.render_ldr_features = clock.wrap("sampling", render_and_wrap)
    trainer.optimizer.step = clock.wrap("optimiser", trainer.optimizer.step)
    backbone.after_step = clock.wrap("density grid", backbone.after_step)


def profile(
    scene: str, method: str, preset: str | None, warmup: int, steps: int, threads: int, rays: int | None
) -> dict:
    torch.set_num_threads(threads)
    spec = RunSpec(backbone="nerf", method=method, preset=preset, scene=scene)
    trainer = build_run(
        spec,
        cached_scene(scene, spec.exposure_index),
        Path(tempfile.mkdtemp(prefix="nerf_profile_")),
        RunBudget(steps=warmup + steps, max_eval_views=1),
    )
    if rays is not None:
        trainer.backbone.pixel_batch = rays
    for _ in range(warmup):
        trainer.train_step()
    clock = PhaseClock()
    instrument(trainer, clock)
    original_backward = torch.Tensor.backward
    torch.Tensor.backward = clock.wrap("backward", original_backward)
    step_times = []
    try:
        for _ in range(steps):
            started = time.perf_counter()
            clock.wrap("other", trainer.train_step)()
            step_times.append(time.perf_counter() - started)
    finally:
        torch.Tensor.backward = original_backward
    total = sum(step_times)
    return {
        "scene": scene,
        "method": method,
        "preset": preset,
        "threads": threads,
        "warmup": warmup,
        "steps": steps,
        "rays_per_step": trainer.backbone.pixel_batch,
        "mean_step_seconds": total / steps,
        "median_step_seconds": statistics.median(step_times),
        "phases": {phase: clock.seconds[phase] / steps for phase in PHASES},
    }


def markdown(result: dict) -> str:
    total = result["mean_step_seconds"]
    lines = [
        f"{result['scene']}, {result['method']}, preset {result['preset'] or '(default)'}, "
        f"{result['rays_per_step']} rays per step, {result['threads']} threads, steps "
        f"{result['warmup']}..{result['warmup'] + result['steps']}: mean step {1000 * total:.0f} ms",
        "",
        "| phase | ms per step | share |",
        "|---|---|---|",
    ]
    for phase in PHASES:
        seconds = result["phases"][phase]
        lines.append(f"| {phase} | {1000 * seconds:.1f} | {100 * seconds / total:.0f} % |")
    return "\n".join(lines)


def main() -> None:
    parser = args_of.script_parser(__doc__)
    args_of.add_scenes(parser, "demo")
    args_of.add_methods(parser, "mono")
    parser.add_argument("--preset", default=None)
    args_of.add_count(parser, "--warmup", 60, "training steps before timing")
    args_of.add_count(parser, "--steps", 40, help="timed steps")
    args_of.add_threads(parser)
    parser.add_argument("--rays", type=args_of.COUNT, default=None, help="rays per step (default: the preset's)")
    parser.add_argument("--json", type=Path, default=None, help="also write the result here")
    args = parser.parse_args()
    result = profile(args.scene, args.method, args.preset, args.warmup, args.steps, args.threads, args.rays)
    print(markdown(result))
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
