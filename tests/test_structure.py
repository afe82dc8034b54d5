"""The package's structure: no import cycle among its modules, counting the
imports inside functions (which hide a cycle rather than remove it), and no
import to a higher floor of docs/layout.md's layers table; and the tests':
what they share, they import from tests/helpers.py."""

import ast
import os
import shutil

import cpl_keras

PACKAGE = os.path.dirname(os.path.abspath(cpl_keras.__file__))


def _modules(package=PACKAGE):
    """``{dotted name: path}`` of every module of ``package`` (a folder)."""
    found = {}
    for folder, _, names in os.walk(package):
        for name in names:
            if name.endswith(".py"):
                path = os.path.join(folder, name)
                dotted = os.path.relpath(path[:-3], os.path.dirname(package)).replace(os.sep, ".")
                found[dotted[: -len(".__init__")] if dotted.endswith(".__init__") else dotted] = path
    return found


def package_imports(path, modules):
    """``[(line, module)]``: each import of one of ``modules`` in the file at
    ``path``, anywhere in its code (``from a.b import c`` counts as importing
    ``a.b.c`` when that is a module, else ``a.b``)."""
    def resolve(name):
        while name and name not in modules:
            name = name.rpartition(".")[0]
        return name

    with open(path) as f:
        tree = ast.parse(f.read())
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            names = [f"{node.module}.{alias.name}" for alias in node.names]
        else:
            continue
        found += [(node.lineno, resolve(n)) for n in names if n.startswith("cpl_keras")]
    return found


def import_graph(package=PACKAGE):
    """``{module: set of package modules it imports}``, anywhere in its code."""
    modules = _modules(package)
    return {module: {target for _, target in package_imports(path, modules)} - {module, ""}
            for module, path in modules.items()}


def cycles(graph):
    """The strongly connected components of more than one module (Tarjan)."""
    index, low, stack, on_stack, found = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_cycle_finder_finds_a_cycle():
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set()}) == []


def test_no_import_cycle_in_the_package():
    graph = import_graph()
    assert "cpl_keras.files" in graph and graph["cpl_keras.files"] == set()  # the ground floor
    assert graph["cpl_keras.data.writer"] >= {"cpl_keras.files"}
    assert cycles(graph) == []


# ---------------------------------------------------------------------------
# Imports flow down the layers of docs/layout.md
# ---------------------------------------------------------------------------
#: The layers' order, in docs/layout.md's ```layers block.
LAYOUT = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "docs",
                      "layout.md")


def read_layers(path=LAYOUT):
    """The floors of the ```layers block in ``path``, ground floor first:
    the names on each line (``runs`` a module, ``data/`` a package with all
    its modules, ``__init__`` the package's own; ``#`` starts a comment)."""
    with open(path) as f:
        text = f.read()
    assert "```layers\n" in text, f"{path}: no ```layers block"
    block = text.split("```layers\n", 1)[1].split("```", 1)[0]
    lines = (line.partition("#")[0].split() for line in block.splitlines())
    return [names for names in lines if names]


def _named_by(module, name):
    """Whether the layers table's ``name`` names ``module`` (a dotted name)."""
    short = module.partition(".")[2] or "__init__"
    dotted = name.rstrip("/").replace("/", ".")
    return short == dotted or (name.endswith("/") and short.startswith(dotted + "."))


def floors_of(modules, layers):
    """``({module: (floor, name)}, [problem])``: each module's floor (1, the
    ground floor, up) and the table's name for it, and a line for each module
    on no floor or on two and for each name of the table that names no module."""
    floors, problems = {}, []
    for module in sorted(modules):
        found = [(floor, name) for floor, names in enumerate(layers, 1) for name in names
                 if _named_by(module, name)]
        if len(found) == 1:
            floors[module] = found[0]
        elif not found:
            problems.append(f"{module}: on no floor of the layers table ({LAYOUT})")
        else:
            problems.append(f"{module}: on more than one floor, as {found}")
    problems += [f"the layers table names {name!r} (floor {floor}), which is no module"
                 for floor, names in enumerate(layers, 1) for name in names
                 if not any(_named_by(module, name) for module in modules)]
    return floors, problems


def layer_breaches(package=PACKAGE, layers=None):
    """A line for each import to a higher floor (``file:line: module (floor
    a: name) imports module (floor b: name)``), imports inside functions
    included, after the table's own problems (``floors_of``)."""
    modules = _modules(package)
    floors, problems = floors_of(modules, read_layers() if layers is None else layers)
    for module, path in sorted(modules.items()):
        where = os.path.relpath(path, os.path.dirname(package))
        problems += [f"{where}:{line}: {module} (floor %d: %s) imports {target} (floor %d: %s)"
                     % (floors[module] + floors[target])
                     for line, target in sorted(set(package_imports(path, modules)))
                     if module in floors and target in floors
                     and floors[target][0] > floors[module][0]]
    return problems


def test_imports_flow_down_the_layers_of_docs_layout():
    """Every module of the package is on one floor of docs/layout.md's layers
    table and imports only from its own floor or lower ones."""
    layers = read_layers()
    assert layers[0][0] == "files" and "commands/" in layers[-1] and len(layers) >= 10
    assert layer_breaches() == []


def test_the_layers_check_names_an_import_to_a_higher_floor(tmp_path):
    """On a copy of the package with an import to a higher floor (at module
    level, and inside a function) and a module the table leaves out, the
    check names each."""
    copy = tmp_path / "cpl_keras"
    shutil.copytree(PACKAGE, copy, ignore=lambda folder, names: [
        name for name in names if name == "__pycache__"
        or not (name.endswith(".py") or os.path.isdir(os.path.join(folder, name)))])
    files_lines = len((copy / "files.py").read_text().splitlines())
    with open(copy / "files.py", "a") as f:
        f.write("import cpl_keras.reproduce\n")
    camera_lines = len((copy / "camera.py").read_text().splitlines())
    with open(copy / "camera.py", "a") as f:
        f.write("def _up():\n    from cpl_keras import runs\n")
    (copy / "annex.py").write_text("")
    layers = read_layers()
    floor = {name: number for number, names in enumerate(layers, 1) for name in names}
    assert sorted(layer_breaches(str(copy), layers)) == sorted([
        f"cpl_keras/files.py:{files_lines + 1}: cpl_keras.files (floor {floor['files']}: files) "
        f"imports cpl_keras.reproduce (floor {floor['reproduce/']}: reproduce/)",
        f"cpl_keras/camera.py:{camera_lines + 2}: cpl_keras.camera (floor {floor['camera']}: "
        f"camera) imports cpl_keras.runs (floor {floor['runs']}: runs)",
        f"cpl_keras.annex: on no floor of the layers table ({LAYOUT})"])
    # a name of the table that is no module, and a module on two floors
    assert floors_of({"cpl_keras.data.pair": ""}, [["data/"], ["data/pair", "gone"]])[1] == [
        "cpl_keras.data.pair: on more than one floor, as [(1, 'data/'), (2, 'data/pair')]",
        "the layers table names 'gone' (floor 2), which is no module"]


#: Third-party modules heavy enough to import only where they are used.
HEAVY = {"keras", "jax", "jaxlib", "matplotlib", "cv2", "h5py", "skimage", "scipy", "PIL"}
#: Imports inside functions that are there by design: the lazy attributes of
#: ``cpl_keras`` and ``cpl_keras.models`` (Keras, or numpy, on first use), and the data
#: generator's worker task taken from the imported module, not ``__main__``.
LAZY_BY_DESIGN = {("cpl_keras", "cpl_keras.models"), ("cpl_keras.models", "importlib"),
                  # (numpy, through the camera model: ``from cpl_keras import cli``,
                  # every command's first import, stays a few milliseconds, so its
                  # Ctrl-C guard is in place at once)
                  ("cpl_keras", "cpl_keras.camera"),
                  ("cpl_keras.data.generate", "cpl_keras.data.generate"),
                  # (``import cpl_keras`` imports cpl_keras.backend, to check Keras's
                  # backend when Keras is imported; importlib.metadata, for the versions
                  # a run records, would double the time of ``from cpl_keras import cli``)
                  ("cpl_keras.backend", "importlib.metadata")}


def _top_level_imports(module, modules):
    with open(modules[module]) as f:
        tree = ast.parse(f.read())
    names = set()
    for node in tree.body:
        if isinstance(node, ast.Import):
            names |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            names.add(node.module)
            names |= {f"{node.module}.{alias.name}" for alias in node.names
                      if f"{node.module}.{alias.name}" in modules}
    return names


def function_level_imports():
    """``[(module, imported name)]`` of every import inside a function."""
    found = []
    for module, path in _modules().items():
        with open(path) as f:
            tree = ast.parse(f.read())
        for function in ast.walk(tree):
            if not isinstance(function, (ast.FunctionDef, ast.AsyncFunctionDef)):
                continue
            for node in ast.walk(function):
                if isinstance(node, ast.Import):
                    found += [(module, alias.name) for alias in node.names]
                elif isinstance(node, ast.ImportFrom) and node.module:
                    inner = [f"{node.module}.{a.name}" for a in node.names
                             if f"{node.module}.{a.name}" in _modules()]
                    found += [(module, name) for name in (inner or [node.module])]
    return found


def imports_heavy(name, modules, seen=None):
    """Whether importing ``name`` imports a HEAVY module (for the package's
    own modules: through their top-level imports, and their packages')."""
    if name.split(".")[0] in HEAVY:
        return True
    if not name.startswith("cpl_keras"):
        return False
    seen = set() if seen is None else seen
    parts = name.split(".")
    chain = [".".join(parts[:i]) for i in range(1, len(parts) + 1)]
    for module in chain:
        if module in seen or module not in modules:
            continue
        seen.add(module)
        if any(imports_heavy(n, modules, seen) for n in _top_level_imports(module, modules)):
            return True
    return False


def test_imports_inside_functions_are_heavy_ones_only():
    """The package's own modules and the standard library are imported at
    the top of a module; inside a function only what imports Keras, JAX,
    matplotlib, OpenCV, h5py, scikit-image, SciPy or PIL (or a package module that does), so
    that the command lines start without them."""
    modules = _modules()
    light = sorted({(module, name) for module, name in function_level_imports()
                    if not imports_heavy(name, modules)} - LAZY_BY_DESIGN)
    assert light == []
    # and the check can fail: a light import is light, a Keras module heavy
    assert not imports_heavy("cpl_keras.runs", modules)
    assert imports_heavy("cpl_keras.models.losses", modules) and imports_heavy("cv2", modules)


def test_command_line_modules_start_without_keras():
    import subprocess
    import sys

    code = ("import sys, cpl_keras.training, cpl_keras.runs, cpl_keras.evaluation, "
            "cpl_keras.reproduce, cpl_keras.calibrate, cpl_keras.graph, cpl_keras.data.generate, "
            "cpl_keras.real.build, cpl_keras.commands.train, cpl_keras.commands.evaluate, "
            "cpl_keras.console; print(sorted(m for m in ('keras', 'jax', 'cv2', 'h5py', "
            "'matplotlib') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120, check=True).stdout
    assert out.strip() == "[]"


def test_every_error_of_the_package_is_an_errors_error():
    """Each module's one-line error derives from ``cpl_keras.errors.Error``
    (itself a ValueError), so one except clause catches them all."""
    import importlib
    import inspect

    from cpl_keras.errors import Error

    found = {}
    for module in _modules():
        if module.endswith("__main__"):
            continue
        for name, value in vars(importlib.import_module(module)).items():
            if (inspect.isclass(value) and name.endswith("Error")
                    and value.__module__ == module and value is not Error):
                found[f"{module}.{name}"] = issubclass(value, Error)
    assert len(found) >= 8, found
    assert {name for name, ok in found.items() if not ok} == set()
    assert issubclass(Error, ValueError)


#: The house's limits: a module a reader takes in at once, a function that
#: reads top to bottom, and imports of the package's own modules at the top
#: (inside a function only where a module imports Keras and the caller must
#: start without it).
MAX_MODULE_LINES = 400
MAX_FUNCTION_LINES = 60
MAX_OWN_FUNCTION_LEVEL_IMPORTS = 10
#: What may pass those limits, each with its reason; the test fails when one
#: of them is back under its limit (then it leaves this list) or grows past
#: the size given here.
EXCEPTIONS = {
    "cpl_keras.reproduce.page.write_report": (75, "REPORT.md's sections in the order a reader "
                                                  "meets them"),
    "cpl_keras.data.scenes._make_objects": (70, "a town's objects, one kind after another"),
}


def oversized(limit_module=MAX_MODULE_LINES, limit_function=MAX_FUNCTION_LINES,
              exceptions=None):
    """``[(what, lines)]``: modules over ``limit_module`` lines and functions
    (from ``def`` to their last line) over ``limit_function``, but those of
    ``exceptions`` within the size given there."""
    exceptions = exceptions or {}
    found = []
    for module, path in _modules().items():
        with open(path) as f:
            text = f.read()
        if len(text.splitlines()) > exceptions.get(module, (limit_module,))[0]:
            found.append((module, len(text.splitlines())))
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                lines = node.end_lineno - node.lineno + 1
                name = f"{module}.{node.name}"
                if lines > exceptions.get(name, (limit_function,))[0]:
                    found.append((name, lines))
    return found


def test_modules_and_functions_stay_readable():
    assert oversized(exceptions=EXCEPTIONS) == []
    # each exception is still needed: it passes the house's limit
    needed = {what for what, _ in oversized()}
    assert set(EXCEPTIONS) <= needed, set(EXCEPTIONS) - needed
    own = [(m, n) for m, n in function_level_imports() if n.startswith("cpl_keras")]
    assert len(own) <= MAX_OWN_FUNCTION_LEVEL_IMPORTS, own
    # and the check can fail: tighter limits find the longest module and function
    assert any("." in what for what, _ in oversized(limit_function=40))
    assert any(lines > 300 for _, lines in oversized(limit_module=300))


# ---------------------------------------------------------------------------
# The tests' own imports
# ---------------------------------------------------------------------------
TESTS = os.path.dirname(os.path.abspath(__file__))


def _is_test_module(name):
    """Whether the module ``name`` is a test file's or conftest's (as a
    top-level module or under ``tests.``)."""
    name = name.removeprefix("tests.")
    return name.startswith("test_") or name == "conftest"


def imports_of_test_modules(source, filename):
    """``["file:line: module"]`` for each import in ``source`` of a test
    module or of conftest (``import test_x``, ``from conftest import ...``,
    ``from tests.test_x import ...``, ``from tests import test_x``)."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            module = node.module or ""
            names = [module] if module not in ("", "tests") else \
                [f"{module}.{alias.name}".lstrip(".") for alias in node.names]
        else:
            continue
        found += [f"{filename}:{node.lineno}: {name}" for name in names if _is_test_module(name)]
    return found


def test_tests_import_helpers_from_helpers_only():
    """A test file (and conftest.py, and helpers.py) imports what it shares
    from tests/helpers.py, never from another test file or from conftest."""
    found = []
    for name in sorted(os.listdir(TESTS)):
        if name.endswith(".py") and (name.startswith("test_") or name in ("conftest.py",
                                                                             "helpers.py")):
            with open(os.path.join(TESTS, name)) as f:
                found += imports_of_test_modules(f.read(), f"tests/{name}")
    assert found == [], found
    # and the check can fail
    bad = ("import os, test_a\nfrom conftest import x\nfrom tests.test_b import y\n"
           "from tests import test_c, helpers\nfrom helpers import REPO\nimport tests.conftest\n"
           "def f():\n    from test_d import z\n")
    assert sorted(imports_of_test_modules(bad, "t.py")) == [
        "t.py:1: test_a", "t.py:2: conftest", "t.py:3: tests.test_b", "t.py:4: tests.test_c",
        "t.py:6: tests.conftest", "t.py:8: test_d"]


def test_calibration_imports_nothing_of_evaluation():
    """Inference apart from evaluation: calibrating a pair runs the forward
    pass of ``models.inference`` and loads no table or score code."""
    import subprocess
    import sys

    code = ("import sys, cpl_keras.calibration, cpl_keras.calibrate; "
            "print(sorted(m for m in sys.modules if m.startswith('cpl_keras.evaluation')))")
    done = subprocess.run([sys.executable, "-c", code], cwd=os.path.dirname(TESTS),
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0 and done.stdout.strip() == "[]", (done.stdout, done.stderr)


def test_the_model_factory_and_the_run_plan_take_few_parameters():
    """``build_model`` takes at most 6 parameters and ``plan_run`` at most 8
    (the knobs travel in ``ModelOptions`` and ``TrainingOptions``)."""
    import inspect

    from cpl_keras.models.factory import build_model
    from cpl_keras.training.planning import plan_run

    assert len(inspect.signature(build_model).parameters) <= 6
    assert len(inspect.signature(plan_run).parameters) <= 8
