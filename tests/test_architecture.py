"""The import graph: one one-clip pipeline under every runner, no runner in another's insides.

Parsed with `ast` from the source files (imports inside functions count too), so a change that
makes the pipeline reach back into a runner, or the daemon into the batch, fails here.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
RUNNERS = {"kbbatch.batch", "kbbatch.watch", "kbbatch.ray_executor", "kbbatch.cli",
           "kbbatch.__main__", "kbbatch.entry"}
"""Modules that run many clips (or a command line); everything else makes or serves one clip."""


def module_name(path: Path) -> str:
    relative = path.relative_to(ROOT).with_suffix("")
    parts = list(relative.parts)
    if parts[0] in ("planners", "presets"):  # installed inside kbbatch (pyproject package-dir)
        parts.insert(0, "kbbatch")
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def package_modules() -> dict[str, Path]:
    files = [*ROOT.glob("kbbatch/**/*.py"), *ROOT.glob("planners/*.py"),
             *ROOT.glob("presets/*.py")]
    return {module_name(path): path for path in files}


def imports_of(path: Path) -> list[tuple[str, str | None]]:
    """(module, name) for every import in a file; name is None for `import module`."""
    found: list[tuple[str, str | None]] = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            found += [(alias.name, None) for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found += [(node.module, alias.name) for alias in node.names]
            # `from kbbatch import batch` imports the module kbbatch.batch
            found += [(f"{node.module}.{alias.name}", None) for alias in node.names]
    return found


def test_the_package_is_found():
    modules = package_modules()
    assert {"kbbatch.pipeline", "kbbatch.batch", "kbbatch.watch", "kbbatch.ray_executor",
            "kbbatch.planners.auto", "kbbatch.depth"} <= set(modules)


def test_the_pipeline_and_the_stages_never_import_a_runner():
    offenders = [f"{name} imports {module}"
                 for name, path in package_modules().items() if name not in RUNNERS
                 for module, _ in imports_of(path) if module in RUNNERS]
    assert offenders == []


def test_the_daemon_and_the_ray_executor_do_not_import_the_batch_runner():
    modules = package_modules()
    offenders = [f"{name} imports {module}" for name in ("kbbatch.watch", "kbbatch.ray_executor")
                 for module, _ in imports_of(modules[name]) if module == "kbbatch.batch"]
    assert offenders == []


def test_no_module_imports_another_modules_private_names():
    files = {**package_modules(), **{f"benchmarks.{p.stem}": p
                                     for p in ROOT.glob("benchmarks/*.py")}}
    offenders = [f"{name} imports {module}.{imported}"
                 for name, path in files.items() for module, imported in imports_of(path)
                 if module.startswith("kbbatch") and imported and imported.startswith("_")
                 and not imported.startswith("__")]
    assert offenders == []


STAGE_STEPS = {"prepare_scene", "render_clip_frames", "encode_frames", "estimate_disparity",
               "build_extended_cloud", "render_frame"}
"""The pipeline's steps: a runner that imports one is making clips its own way."""


def test_every_runner_makes_its_clips_with_the_one_pipeline():
    modules = package_modules()
    uses = {runner: set(imports_of(modules[runner]))
            for runner in ("kbbatch.batch", "kbbatch.watch", "kbbatch.ray_executor")}
    assert ("kbbatch.pipeline", "LocalExecutor") in uses["kbbatch.batch"]
    assert ("kbbatch.pipeline", "make_clip") in uses["kbbatch.watch"]
    assert ("kbbatch.pipeline", "make_clip") in uses["kbbatch.ray_executor"]
    offenders = [f"{runner} imports {name}" for runner, imported in uses.items()
                 for _, name in imported if name in STAGE_STEPS]
    assert offenders == []
