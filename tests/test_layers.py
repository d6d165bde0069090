"""The package's layers import one way (read from the source, over the AST, without importing it).

Layers, lowest first (a module may import its own layer and those below it, never above):

0. ``errors``, ``params``, ``tolerances`` -- the exception type, the parameter table, the named
   tolerances
1. ``core`` -- NumPy only: the data model, validation, boxes, levels, derived fields, the kd-tree,
   the ``.npz`` layout, the float64 reference model
2. ``readers``, ``synthetic`` -- file formats; synthetic datasets and the scenes' data files
3. ``kernels`` -- Dr.Jit: device arrays, reconstruction, roots, traversal, the methods
4. ``plugin`` -- Mitsuba: options, shading, the integrator, loading scenes
5. ``workflows`` -- rendering files, movies, the viewer
6. ``evaluation`` -- benchmarks, peers, the stability suite, reference images
7. ``cli``, ``__main__``

The package root (``mi_amr/__init__.py``) is the public facade: it imports layers 0-2 when it is
imported, and the rest only on first use.
"""

import ast
import subprocess
import sys
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "mi_amr"
LAYERS = {
    "mi_amr.errors": 0, "mi_amr.params": 0, "mi_amr.tolerances": 0,
    "mi_amr.core": 1,
    "mi_amr.readers": 2, "mi_amr.synthetic": 2,
    "mi_amr.kernels": 3,
    "mi_amr.plugin": 4,
    "mi_amr.workflows": 5,
    "mi_amr.evaluation": 6,
    "mi_amr.cli": 7, "mi_amr.__main__": 7,
}
ROOT_EAGER_MAX = 2          # what `import mi_amr` may pull in
ROOT_MAX = 4                # what the facade may import on first use
# Third-party modules that only some layers may import.
RESTRICTED = {"drjit": 3, "mitsuba": 4}


def module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def layer_of(name: str):
    best = None
    for prefix, rank in LAYERS.items():
        if name == prefix or name.startswith(prefix + "."):
            if best is None or len(prefix) > len(best[0]):
                best = (prefix, rank)
    return None if best is None else best[1]


def imports(path: Path):
    """``(imported module, line, at module level?)`` for every import in ``path``, relative
    imports resolved."""
    tree = ast.parse(path.read_text())
    package = module_name(path) if path.name == "__init__.py" else \
        module_name(path).rpartition(".")[0]
    top = {id(n) for n in tree.body}
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(a.name, node.lineno, id(node) in top) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module
            # "from pkg import sub" imports the submodule when there is one.
            for a in node.names:
                sub = f"{mod}.{a.name}"
                is_module = (PACKAGE.parent / Path(*sub.split("."))).with_suffix(".py").exists() \
                    or (PACKAGE.parent / Path(*sub.split("."))).is_dir()
                out.append((sub if is_module else mod, node.lineno, id(node) in top))
    return out


SOURCES = sorted(PACKAGE.rglob("*.py"))


def test01_every_module_has_a_layer():
    missing = [module_name(p) for p in SOURCES
               if module_name(p) != "mi_amr" and layer_of(module_name(p)) is None]
    assert not missing, f"modules outside every layer (add them to LAYERS): {missing}"


def test02_imports_go_down_the_layers_only():
    wrong = []
    for path in SOURCES:
        name = module_name(path)
        if name == "mi_amr":
            continue
        rank = layer_of(name)
        for target, line, _ in imports(path):
            if target == "mi_amr":
                wrong.append(f"{name}:{line} imports the package facade 'mi_amr'")
                continue
            t = layer_of(target)
            if t is not None and t > rank:
                wrong.append(f"{name}:{line} (layer {rank}) imports {target} (layer {t})")
            top = target.split(".")[0]
            if top in RESTRICTED and rank < RESTRICTED[top]:
                wrong.append(f"{name}:{line} (layer {rank}) imports {top}, allowed from layer "
                             f"{RESTRICTED[top]} up")
    assert not wrong, "imports against the layers:\n" + "\n".join(wrong)


def test03_the_facade_imports_little_eagerly():
    root = PACKAGE / "__init__.py"
    wrong = []
    for target, line, module_level in imports(root):
        t = layer_of(target)
        if t is None:
            continue
        limit = ROOT_EAGER_MAX if module_level else ROOT_MAX
        if t > limit:
            wrong.append(f"mi_amr/__init__.py:{line} imports {target} (layer {t} > {limit})")
    assert not wrong, "\n".join(wrong)


def test04_no_import_cycles():
    graph = {}
    for path in SOURCES:
        name = module_name(path)
        graph[name] = {t for t, _, _ in imports(path)
                       if t.startswith("mi_amr") and t != name and t != "mi_amr"}
    # Tarjan's strongly connected components.
    index, low, stack, on, cycles = {}, {}, [], set(), []
    counter = [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
            if w not in graph:
                continue
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                cycles.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    assert not cycles, f"import cycles: {cycles}"


def test05_import_mi_amr_needs_numpy_only():
    """``import mi_amr`` (data model, readers, datasets) loads neither Dr.Jit nor Mitsuba."""
    code = ("import sys, mi_amr; bad = [m for m in ('drjit', 'mitsuba') if m in sys.modules]; "
            "print(bad); sys.exit(1 if bad else 0)")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          cwd=PACKAGE.parent)
    assert proc.returncode == 0, proc.stdout + proc.stderr


@pytest.mark.parametrize("limit", [80])
def test06_no_function_is_longer_than_80_lines(limit):
    long = []
    for path in SOURCES:
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                n = node.end_lineno - node.lineno + 1
                if n > limit:
                    long.append(f"{path.relative_to(PACKAGE.parent)}:{node.lineno} "
                                f"{node.name} ({n} lines)")
    assert not long, "functions over 80 lines:\n" + "\n".join(long)


def test07_the_integrator_module_is_thin():
    lines = len((PACKAGE / "plugin" / "integrator.py").read_text().splitlines())
    assert lines < 250, f"plugin/integrator.py has {lines} lines"


@pytest.mark.parametrize("limit", [6])
def test08_no_kernel_function_takes_more_than_6_parameters(limit):
    """Kernel functions (every function in a module of ``mi_amr.kernels``, as
    ``../shared/tools/layout_figures.py`` counts them: positional and keyword-only parameters,
    ``self`` and ``cls`` aside) take a ray context or a small record instead of long argument
    lists."""
    wide = []
    for path in SOURCES:
        if not module_name(path).startswith("mi_amr.kernels."):
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                a = node.args
                n = len([x for x in a.posonlyargs + a.args + a.kwonlyargs
                         if x.arg not in ("self", "cls")])
                if n > limit:
                    wide.append(f"{path.relative_to(PACKAGE.parent)}:{node.lineno} "
                                f"{node.name} ({n} parameters)")
    assert not wide, "kernel functions over 6 parameters:\n" + "\n".join(wide)
