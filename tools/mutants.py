"""Mutation testing of the modules that produce the reported numbers and train the model.

    make mutants                                   # every target (hours on 2 busy cores; nice -n 19)
    .venv/bin/python tools/mutants.py --targets metrics converters
    .venv/bin/python tools/mutants.py --list --targets methods          # the mutants, not run
    .venv/bin/python tools/mutants.py --targets methods --ids 12 40     # some of them
    .venv/bin/python tools/mutants.py --rerun outputs/mutants/results.json   # the survivors of a run

A mutant is one small edit of the syntax tree (an operator, a comparison, a constant, a
swapped argument, a dropped call or statement). Each one is run against only its target's
tests (pytest -x); it is killed when a test fails or it runs past its timeout. Mutants never
touch the files: a forked child imports the mutated module through an import hook, after the
parent has imported torch and the other heavy libraries once, so a mutant costs only its tests.
Results: OUT/results.json (every mutant, its status and seconds) and a Markdown summary on stdout.
docs/testing.md has the last full run, and the survivors judged equivalent with the reason.
"""

import argparse
import ast
import contextlib
import copy
import importlib.abc
import importlib.util
import json
import os
import signal
import sys
import time
from collections.abc import Iterator
from dataclasses import asdict, dataclass
from pathlib import Path

from mutation_targets import TARGETS, Target

ROOT = Path(__file__).resolve().parents[1]
PROJECT_PACKAGES = (
    "mono_hdr_plugin",
    "backbones",
    "register_backbone",
    "register_method",
    "register_layout",
    "known_render",
    "gs_scenes",
    "nerf_scenes",
    "hard_scenes",
    "conftest",
)


# Method calls whose removal leaves a value of the same kind: `x.detach()` -> `x` and so on
# (not functions of a module: dropping `torch.mean(...)` to `torch` only makes a crash).
MODULE_NAMES = {"torch", "F", "nn", "math", "np"}
DROPPABLE_METHODS = {
    "detach",
    "clamp",
    "clamp_min",
    "clamp_max",
    "contiguous",
    "float",
    "double",
    "clone",
    "abs",
    "squeeze",
    "unsqueeze",
    "mean",
    "sum",
    "item",
}
BINARY_SWAPS = {
    ast.Add: ast.Sub,
    ast.Sub: ast.Add,
    ast.Mult: ast.Div,
    ast.Div: ast.Mult,
    ast.FloorDiv: ast.Div,
    ast.Mod: ast.FloorDiv,
    ast.Pow: ast.Mult,
    ast.BitAnd: ast.BitOr,
    ast.BitOr: ast.BitAnd,
}
COMPARE_SWAPS = {
    ast.Lt: ast.LtE,
    ast.LtE: ast.Lt,
    ast.Gt: ast.GtE,
    ast.GtE: ast.Gt,
    ast.Eq: ast.NotEq,
    ast.NotEq: ast.Eq,
    ast.Is: ast.IsNot,
    ast.IsNot: ast.Is,
    ast.In: ast.NotIn,
    ast.NotIn: ast.In,
}


@dataclass
class Mutant:
    target: str
    id: int
    line: int
    description: str
    source_line: str
    status: str = "not run"  # killed | survived | timeout | not run
    seconds: float = 0.0
    killed_by: str = ""


@dataclass
class _Site:
    line: int
    description: str


def _mutations(node: ast.AST) -> Iterator[tuple[str, object]]:
    """(description, function giving the mutated copy of `node`) for every mutation of `node`."""
    if isinstance(node, (ast.BinOp, ast.AugAssign)) and type(node.op) in BINARY_SWAPS:
        new_op = BINARY_SWAPS[type(node.op)]
        yield (f"{type(node.op).__name__} -> {new_op.__name__}", lambda n, new_op=new_op: _replace(n, op=new_op()))
    elif isinstance(node, ast.Compare):
        for index, op in enumerate(node.ops):
            if type(op) in COMPARE_SWAPS:
                new_op = COMPARE_SWAPS[type(op)]

                def swap(n, index=index, new_op=new_op):
                    ops = list(n.ops)
                    ops[index] = new_op()
                    return _replace(n, ops=ops)

                yield f"{type(op).__name__} -> {new_op.__name__}", swap
    elif isinstance(node, ast.BoolOp):
        other = ast.Or if isinstance(node.op, ast.And) else ast.And
        yield f"{type(node.op).__name__} -> {other.__name__}", lambda n, other=other: _replace(n, op=other())
    elif isinstance(node, ast.UnaryOp) and isinstance(node.op, (ast.Not, ast.USub, ast.Invert)):
        yield f"drop unary {type(node.op).__name__}", lambda n: n.operand
    elif isinstance(node, ast.Constant) and type(node.value) in (int, float):
        value = node.value
        new = value + 1
        yield f"{value!r} -> {new!r}", lambda n, new=new: _replace(n, value=new)
    elif isinstance(node, ast.Constant) and isinstance(node.value, bool):
        yield f"{node.value} -> {not node.value}", lambda n: _replace(n, value=not n.value)
    elif isinstance(node, ast.Call):
        positional = [a for a in node.args if not isinstance(a, ast.Starred)]
        if len(positional) >= 2 and len(positional) == len(node.args):

            def swap_args(n):
                args = list(n.args)
                args[0], args[1] = args[1], args[0]
                return _replace(n, args=args)

            yield f"swap the first two arguments of {_call_name(node)}", swap_args
        if (
            isinstance(node.func, ast.Attribute)
            and node.func.attr in DROPPABLE_METHODS
            and not (isinstance(node.func.value, ast.Name) and node.func.value.id in MODULE_NAMES)
        ):
            yield f"drop .{node.func.attr}(...)", lambda n: n.func.value


def _call_name(node: ast.Call) -> str:
    return ast.unparse(node.func) if len(ast.unparse(node.func)) < 40 else "a call"


def _replace(node: ast.AST, **changes) -> ast.AST:
    new = copy.copy(node)
    for key, value in changes.items():
        setattr(new, key, value)
    return new


def _skipped(node: ast.AST) -> bool:
    """Subtrees whose mutants say nothing about behaviour: messages, docstrings, annotations."""
    return isinstance(node, (ast.JoinedStr, ast.Raise, ast.Assert)) or (
        isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant)
    )


class _Walker:
    """Finds mutation sites in order; with `chosen`, returns the tree with only that site mutated."""

    def __init__(self, scopes: tuple[str, ...], chosen: int | None = None):
        self.scopes, self.chosen = scopes, chosen
        self.sites: list[_Site] = []

    def in_scope(self, qualname: str) -> bool:
        if not self.scopes:  # the whole module, module-level constants included
            return True
        return any(qualname == s or qualname.startswith(s + ".") for s in self.scopes)

    def _add_sites(self, node: ast.AST) -> ast.AST:
        replacement = node
        for description, apply in _mutations(node):
            if len(self.sites) == self.chosen:
                replacement = apply(node)
            self.sites.append(_Site(getattr(node, "lineno", 0), description))
        return replacement

    def visit(self, node: ast.AST, qualname: str = "") -> ast.AST:
        if _skipped(node):
            return node
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            qualname = f"{qualname}.{node.name}" if qualname else node.name
            node.args.defaults = [self.visit(d, qualname) for d in node.args.defaults]
            node.args.kw_defaults = [d if d is None else self.visit(d, qualname) for d in node.args.kw_defaults]
            self._visit_body(node, qualname)  # not the decorators (registration) nor the annotations
            return node
        if isinstance(node, ast.ClassDef):
            self._visit_body(node, f"{qualname}.{node.name}" if qualname else node.name)
            return node
        if isinstance(node, ast.AnnAssign):
            if node.value is not None:
                node.value = self.visit(node.value, qualname)
            return node
        replacement = self._add_sites(node) if self.in_scope(qualname) else node
        if replacement is node:
            self._visit_fields(node, qualname)
        return replacement

    def _visit_body(self, node: ast.AST, qualname: str) -> None:
        node.body = self._visit_statements(node.body, qualname)

    def _visit_statements(self, statements: list[ast.stmt], qualname: str) -> list[ast.stmt]:
        kept = []
        for statement in statements:
            result = self._statement_site(statement, self.visit(statement, qualname), qualname)
            if result is not None:
                kept.append(result)
        return kept or [ast.Pass()]

    def _visit_fields(self, node: ast.AST, qualname: str) -> None:
        for name, value in ast.iter_fields(node):
            if name == "annotation":
                continue
            if isinstance(value, list) and value and isinstance(value[0], ast.stmt):
                setattr(node, name, self._visit_statements(value, qualname))
            elif isinstance(value, list):
                setattr(
                    node, name, [self.visit(item, qualname) if isinstance(item, ast.AST) else item for item in value]
                )
            elif isinstance(value, ast.AST):
                setattr(node, name, self.visit(value, qualname))

    def _statement_site(self, original: ast.stmt, result: ast.stmt, qualname: str) -> ast.stmt | None:
        """A call made for its effect (`loss.backward()`, `self.optimizer.step()`) can be dropped."""
        if not (self.in_scope(qualname) and isinstance(original, ast.Expr) and isinstance(original.value, ast.Call)):
            return result
        dropped = len(self.sites) == self.chosen
        self.sites.append(_Site(original.lineno, f"drop the statement {_call_name(original.value)}(...)"))
        return None if dropped else result


def enumerate_mutants(name: str, target: Target) -> list[Mutant]:
    source = (ROOT / target.path).read_text()
    lines = source.splitlines()
    walker = _Walker(target.scopes)
    walker.visit(ast.parse(source))
    return [
        Mutant(name, index, site.line, site.description, lines[site.line - 1].strip() if site.line else "")
        for index, site in enumerate(walker.sites)
    ]


def mutated_code(target: Target, index: int):
    source = (ROOT / target.path).read_text()
    walker = _Walker(target.scopes, chosen=index)
    tree = ast.fix_missing_locations(walker.visit(ast.parse(source)))
    return compile(tree, str(ROOT / target.path), "exec")


class _MutantFinder(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Serves the mutated code for one module name; every other import goes on as usual."""

    def __init__(self, module: str, path: Path, code):
        self.module, self.path, self.code = module, path, code

    def find_spec(self, fullname, path=None, target=None):
        if fullname != self.module:
            return None
        return importlib.util.spec_from_file_location(fullname, self.path, loader=self)

    def create_module(self, spec):
        return None

    def exec_module(self, module):
        exec(self.code, module.__dict__)


def _forget_project_modules(keep: tuple[str, ...] = ("backbones.gs._extension",)) -> None:
    for name in list(sys.modules):
        if name in keep:
            continue
        if any(name == p or name.startswith(p + ".") for p in PROJECT_PACKAGES) or name.startswith("test_"):
            del sys.modules[name]


def preload() -> None:
    """Import everything the project imports (torch, numpy, scikit-image, ...), build the C++
    rasteriser, then forget the project's own modules so each mutant imports them afresh."""
    sys.path[:0] = [str(ROOT), str(ROOT / "examples")]
    import pytest  # noqa: F401 - imported for what it imports

    import mono_hdr_plugin.apps.cli
    import mono_hdr_plugin.training.evaluation
    import mono_hdr_plugin.training.trainer  # noqa: F401 - imported for what it imports
    from backbones.gs._extension import load_extension
    from mono_hdr_plugin.core.registry import BACKBONES

    BACKBONES.available()  # imports every backbone plugin and what it needs
    load_extension()
    for optional in ("skimage.metrics", "hypothesis", "mono_hdr_plugin.apps.studio.source"):
        with contextlib.suppress(ImportError):  # an optional extra that is not installed
            __import__(optional)
    _forget_project_modules()


def run_tests(target: Target, code, timeout: float, log: Path) -> tuple[str, float, str]:
    """Run the target's tests in a forked child with the mutated module (None: the original)."""
    started = time.perf_counter()
    read_end, write_end = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child: never returns
        os.close(read_end)
        try:
            os.chdir(ROOT)
            if code is not None:
                sys.meta_path.insert(0, _MutantFinder(target.module, ROOT / target.path, code))
            with open(log, "w") as output:
                os.dup2(output.fileno(), 1)
                os.dup2(output.fileno(), 2)
                import pytest

                status = pytest.main(["-x", "-q", "-p", "no:cacheprovider", "-m", "not slow", *target.tests])
            os.write(write_end, str(int(status)).encode())
        finally:
            os._exit(0)
    os.close(write_end)
    deadline = started + timeout
    while True:
        done, _ = os.waitpid(pid, os.WNOHANG)
        if done:
            break
        if time.perf_counter() > deadline:
            os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
            os.close(read_end)
            return "timeout", time.perf_counter() - started, ""
        time.sleep(0.05)
    status = os.read(read_end, 16).decode()
    os.close(read_end)
    seconds = time.perf_counter() - started
    failed = ""
    if log.exists():
        for line in log.read_text(errors="replace").splitlines():
            if line.startswith(("FAILED ", "ERROR ")):
                failed = line.split(" ", 1)[1].split(" - ")[0]
                break
    if status == "0":
        return "survived", seconds, ""
    return "killed", seconds, failed or f"pytest exit status {status or 'none (crashed)'}"


def summary(mutants: list[Mutant]) -> str:
    rows = ["| target | mutants | killed | of them by timeout | survived | kill rate |", "|---|---|---|---|---|---|"]
    by_target: dict[str, list[Mutant]] = {}
    for mutant in mutants:
        by_target.setdefault(mutant.target, []).append(mutant)
    for name, items in by_target.items():
        ran = [m for m in items if m.status != "not run"]
        killed = sum(m.status in ("killed", "timeout") for m in ran)
        rate = f"{100 * killed / len(ran):.1f} %" if ran else "-"
        timeouts = sum(m.status == "timeout" for m in ran)
        rows.append(f"| {name} | {len(ran)} | {killed} | {timeouts} | {len(ran) - killed} | {rate} |")
    survivors = [m for m in mutants if m.status == "survived"]
    if survivors:
        rows += ["", "Survivors:", ""]
        rows += [f"- {m.target} #{m.id} line {m.line}: {m.description}: `{m.source_line}`" for m in survivors]
    return "\n".join(rows)


def _combined(earlier: list[Mutant], latest: list[Mutant]) -> list[Mutant]:
    """The earlier run's mutants with the latest results in place of theirs."""
    fresh = {(m.target, m.id, m.description): m for m in latest}
    merged = [fresh.pop((m.target, m.id, m.description), m) for m in earlier]
    return merged + list(fresh.values())


def _parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--targets", nargs="*", choices=sorted(TARGETS), help="default: all")
    parser.add_argument("--ids", nargs="*", type=int, help="run only these mutant ids (of one target)")
    parser.add_argument(
        "--rerun", type=Path, help="results.json of an earlier run: run its survivors and timeouts again"
    )
    parser.add_argument("--list", action="store_true", help="list the mutants and stop")
    parser.add_argument("--out", type=Path, default=ROOT / "outputs" / "mutants")
    return parser.parse_args()


def _selected(args: argparse.Namespace) -> tuple[list[Mutant], list[Mutant]]:
    """(the mutants to run, the earlier run's mutants that are reported with them)."""
    names = args.targets or list(TARGETS)
    mutants = [m for name in names for m in enumerate_mutants(name, TARGETS[name])]
    if args.ids is not None:
        mutants = [m for m in mutants if m.id in args.ids]
    earlier: list[Mutant] = []
    if args.rerun is not None:  # the earlier run's mutants are reported too, with the new results
        earlier = [Mutant(**m) for m in json.loads(args.rerun.read_text())["mutants"]]
        again = {(m.target, m.id, m.description) for m in earlier if m.status in ("survived", "timeout")}
        mutants = [m for m in mutants if (m.target, m.id, m.description) in again]
    return mutants, earlier


def _baseline_seconds(mutants: list[Mutant], out: Path) -> dict[str, float] | None:
    """Seconds each target's tests take unmutated; None (after saying why) when they fail without a mutant."""
    baseline: dict[str, float] = {}
    for name in dict.fromkeys(m.target for m in mutants):
        status, seconds, failed = run_tests(TARGETS[name], None, 3600, out / "baseline.log")
        if status != "survived":
            print(f"{name}: the tests fail WITHOUT a mutant ({failed}); see {out / 'baseline.log'}")
            return None
        baseline[name] = seconds
        print(f"{name}: tests pass unmutated in {seconds:.1f} s", flush=True)
    return baseline


def _run_mutants(
    mutants: list[Mutant], earlier: list[Mutant], baseline: dict[str, float], out: Path, started: float
) -> None:
    """Run every mutant, writing results.json after each so an interrupted run keeps what it found."""
    for count, mutant in enumerate(mutants, 1):
        target = TARGETS[mutant.target]
        code = mutated_code(target, mutant.id)
        mutant.status, mutant.seconds, mutant.killed_by = run_tests(
            target, code, 5 * baseline[mutant.target] + 120, out / "mutant.log"
        )
        print(
            f"[{count}/{len(mutants)}] {mutant.status:8s} {mutant.target} #{mutant.id} line {mutant.line}: "
            f"{mutant.description} ({mutant.seconds:.1f} s)",
            flush=True,
        )
        (out / "results.json").write_text(
            json.dumps(
                {
                    "baseline_seconds": baseline,
                    "elapsed_seconds": time.perf_counter() - started,
                    "mutants": [asdict(m) for m in _combined(earlier, mutants)],
                },
                indent=1,
            )
        )


def main() -> int:
    args = _parse_args()
    mutants, earlier = _selected(args)
    if args.list:
        for m in mutants:
            print(f"{m.target} #{m.id} line {m.line}: {m.description}: {m.source_line}")
        print(f"{len(mutants)} mutants")
        return 0

    args.out.mkdir(parents=True, exist_ok=True)
    preload()
    started = time.perf_counter()
    baseline = _baseline_seconds(mutants, args.out)
    if baseline is None:
        return 2
    _run_mutants(mutants, earlier, baseline, args.out, started)
    print(f"\n{len(mutants)} mutants in {time.perf_counter() - started:.0f} s\n")
    print(summary(_combined(earlier, mutants)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
