"""The private Keras and JAX names the package imports: which, where, why
(a comment above each import), and that they are still where the package
takes them from, so that an upgrade of Keras or JAX that moves one fails
here, by name, rather than inside a training run. Every other Keras or JAX
name the package uses is public. (Their use in a process group:
tests/test_distributed.py.)"""

import ast
import os

import cpl_keras

PACKAGE = os.path.dirname(os.path.abspath(cpl_keras.__file__))
#: module file (relative to the package) -> the private names it imports
PRIVATE = {
    "distributed.py": {"jax._src.distributed",
                       "keras.src.backend.jax.distribution_lib.initialize_rng"},
    "models/backbones.py": {"keras.src.random.seed_generator.global_seed_generator"},
}


def _private_imports(path):
    """``{name: line}`` of the imports of ``keras.src`` and ``jax._src`` in a file."""
    with open(path) as f:
        tree = ast.parse(f.read())
    found = {}
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module:
            names = [f"{node.module}.{alias.name}" for alias in node.names]
        elif isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        else:
            continue
        for name in names:
            if name.startswith(("keras.src", "jax._src")):
                found[name] = node.lineno
    return found


def test_the_package_imports_only_the_listed_private_names_each_with_its_reason():
    found = {}
    for folder, _, names in os.walk(PACKAGE):
        for name in sorted(names):
            if not name.endswith(".py"):
                continue
            path = os.path.join(folder, name)
            imports = _private_imports(path)
            if imports:
                found[os.path.relpath(path, PACKAGE)] = set(imports)
            with open(path) as f:
                lines = f.read().splitlines()
            for imported, line in imports.items():
                above = "\n".join(lines[max(line - 5, 0):line - 1])
                assert "(private:" in above, f"{path}:{line}: {imported} without a why"
    assert found == PRIVATE
    # (and the scan finds one: the backbones' import is there)
    assert "keras.src.random.seed_generator.global_seed_generator" in _private_imports(
        os.path.join(PACKAGE, "models", "backbones.py"))


def test_the_private_names_are_where_the_package_takes_them():
    import jax
    import keras
    from jax._src import distributed as jax_distributed
    from keras.src.backend.jax.distribution_lib import initialize_rng
    from keras.src.random.seed_generator import global_seed_generator

    # the coordination service's client, once jax.distributed.initialize ran
    assert hasattr(jax_distributed.global_state, "client")
    assert (jax_distributed.global_state.client is None) == (not jax.distributed.is_initialized())
    assert callable(initialize_rng)
    state = global_seed_generator().state
    before = state.numpy()
    state.assign(before)  # (read and set, as backbones._random_state_kept does)
    assert keras.ops.convert_to_numpy(state).tolist() == before.tolist()
