"""Import architecture of drake_rus: arrows point one way (docs/design.md, "Layers").

Every module belongs to one layer; a module may import only modules of its own layer or
lower ones, there are no import cycles, the two stations never import each other, and
nothing outside ``drake_rus.reliability`` (fault injection) imports it, except the scenario
schema reading its config dataclass. The checks read the source (ast), so they see imports
inside functions too. A negative test proves the checker fails on a bad graph.
"""

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1] / "drake_rus"

# Lowest first. A module's layer is that of the longest prefix listed; ``*.cli`` modules
# (command-line front ends of any package) are in the top layer.
LAYERS = [
    (
        "core",
        [
            "drake_rus",
            "drake_rus.config_schema",
            "drake_rus.paths",
            "drake_rus.io_utils",
            "drake_rus.progress",
            "drake_rus.provenance",
            "drake_rus.station_interface",
            "drake_rus.extras",
            "drake_rus.tables",
            "drake_rus.control.config",
            "drake_rus.hardware.config",
            "drake_rus.imaging.config",
            "drake_rus.localization.config",
            "drake_rus.reliability.config",
            "drake_rus.scan.config",
            "drake_rus.anatomy.motion",
            "drake_rus.interrupts",
            "drake_rus.executor",
            "drake_rus.pacing",
        ],
    ),
    ("scenario", ["drake_rus.scenario"]),
    (
        "models",
        [
            "drake_rus.robot",
            "drake_rus.anatomy",
            "drake_rus.template",
            "drake_rus.metrics",
            "drake_rus.batch",
        ],
    ),
    ("systems", ["drake_rus.control", "drake_rus.imaging", "drake_rus.localization"]),
    ("stations", ["drake_rus.station", "drake_rus.patient_body", "drake_rus.hardware"]),
    ("dispatch", ["drake_rus.stations"]),
    ("scan", ["drake_rus.scan", "drake_rus.closed_loop", "drake_rus.bringup"]),
    # Offline tools (training the segmenter) sit with the studies: the runtime never imports them.
    (
        "studies",
        [
            "drake_rus.experiments",
            "drake_rus.reliability",
            "drake_rus.rehearsal",
            "drake_rus.imaging.training",
        ],
    ),
    ("front", ["drake_rus.cli", "drake_rus.demo", "drake_rus.render"]),
]
# Allowed exceptions, each with its reason.
ALLOWED = {
    # The scenario schema holds the (ignored by the product) faults section's dataclass.
    ("drake_rus.scenario", "drake_rus.reliability.config"),
}


def module_name(path: Path, root: Path = ROOT) -> str:
    parts = path.relative_to(root.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def layer_of(module: str) -> int:
    if module.split(".")[-1] == "cli" and module != "drake_rus":
        return len(LAYERS) - 1
    best, best_len = None, -1
    for index, (_, prefixes) in enumerate(LAYERS):
        for prefix in prefixes:
            if (module == prefix or module.startswith(prefix + ".")) and len(prefix) > best_len:
                best, best_len = index, len(prefix)
    if best is None:
        raise AssertionError(f"{module} is in no layer: add it to LAYERS in {__file__}")
    return best


def imports_of(path: Path, name: str, modules: set) -> set:
    """drake_rus modules that ``path`` (module ``name``) imports, anywhere in the file."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                up = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(up + ([base] if base else []))
            targets = [base] + [f"{base}.{a.name}" for a in node.names]
        else:
            continue
        for target in targets:
            # The deepest drake_rus module named by the import.
            while target and target not in modules:
                target = target.rpartition(".")[0]
            if target and target != name:
                found.add(target)
    return found


def import_graph(root: Path = ROOT) -> dict:
    files = {module_name(p, root): p for p in root.rglob("*.py")}
    modules = set(files)
    return {name: imports_of(path, name, modules) for name, path in files.items()}


def violations(graph: dict) -> list[str]:
    out = []
    for module, targets in graph.items():
        for target in sorted(targets):
            if target == "drake_rus" or module.startswith(target + "."):
                continue  # a package's own __init__ (re-exports) is not an arrow up
            if (module, target) in ALLOWED:
                continue
            if layer_of(target) > layer_of(module):
                out.append(
                    f"{module} ({LAYERS[layer_of(module)][0]}) imports {target} "
                    f"({LAYERS[layer_of(target)][0]}): a higher layer"
                )
            if target.startswith("drake_rus.reliability") and not (
                module.startswith("drake_rus.reliability") or layer_of(module) == len(LAYERS) - 1
            ):
                out.append(f"{module} imports fault injection {target}")
            hardware = ("drake_rus.hardware", "drake_rus.station")
            if (module.startswith(hardware[0]) and target == hardware[1]) or (
                module == hardware[1] and target.startswith(hardware[0])
            ):
                out.append(f"{module} imports {target}: the stations never import each other")
    return out


def cycles(graph: dict) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan)."""
    index, low, stack, on, out, counter = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                out.append(sorted(component))

    for v in graph:
        if v not in index:
            visit(v)
    return out


def test_every_module_has_a_layer():
    for module in import_graph():
        layer_of(module)


def test_imports_point_down_only():
    assert violations(import_graph()) == []


def test_no_import_cycles():
    assert cycles(import_graph()) == []


def test_the_checker_catches_bad_arrows(tmp_path):
    """A fake package where the sim station imports the hardware station, a control module
    imports the scan, the scan imports fault injection and two modules import each other:
    every one is reported."""
    pkg = tmp_path / "drake_rus"
    files = {
        "__init__.py": "",
        "station.py": "from drake_rus.hardware.station import MakeHardwareStation\n",
        "hardware/__init__.py": "",
        "hardware/station.py": "X = 1\n",
        "control/__init__.py": "",
        "control/laws.py": "def f():\n    from drake_rus.scan.run import RunScan\n",
        "scan/__init__.py": "",
        "scan/run.py": "import drake_rus.reliability.faults\nfrom . import diagram\n",
        "scan/diagram.py": "from drake_rus.scan import run\n",
        "reliability/__init__.py": "",
        "reliability/faults.py": "",
    }
    for rel, text in files.items():
        (pkg / rel).parent.mkdir(parents=True, exist_ok=True)
        (pkg / rel).write_text(text)
    graph = import_graph(pkg)
    found = "\n".join(violations(graph))
    assert (
        "drake_rus.station imports drake_rus.hardware.station: the stations never import each other"
    ) in found
    assert "drake_rus.control.laws (systems) imports drake_rus.scan.run" in found
    assert "drake_rus.scan.run imports fault injection drake_rus.reliability.faults" in found
    assert ["drake_rus.scan.diagram", "drake_rus.scan.run"] in cycles(graph)


@pytest.mark.parametrize(
    "module,layer",
    [
        ("drake_rus.anatomy.cli", "front"),
        ("drake_rus.robot.model", "models"),
        ("drake_rus.scan.run", "scan"),
    ],
)
def test_layer_assignment(module, layer):
    assert LAYERS[layer_of(module)][0] == layer


def function_level_imports(root: Path = ROOT) -> list[str]:
    """drake_rus imports inside functions or classes (hidden dependencies)."""
    out = []
    for path in sorted(root.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if (
                isinstance(node, ast.ImportFrom)
                and node.col_offset > 0
                and (node.level or (node.module or "").startswith("drake_rus"))
            ):
                out.append(f"{path.relative_to(root.parent)}:{node.lineno} {ast.unparse(node)}")
            elif (
                isinstance(node, ast.Import)
                and node.col_offset > 0
                and any(a.name.startswith("drake_rus") for a in node.names)
            ):
                out.append(f"{path.relative_to(root.parent)}:{node.lineno} {ast.unparse(node)}")
    return out


def test_internal_imports_are_at_module_top():
    """Every drake_rus import is at the top of its module, where a reader and this test see
    the dependency (only third-party optional libraries may be imported lazily)."""
    assert function_level_imports() == []


def test_the_hidden_import_check_can_fail(tmp_path):
    pkg = tmp_path / "drake_rus"
    pkg.mkdir()
    (pkg / "a.py").write_text("def f():\n    from drake_rus.b import g\n    return g\n")
    (pkg / "b.py").write_text("import numpy\n\ndef g():\n    import scipy\n")
    assert function_level_imports(pkg) == ["drake_rus/a.py:2 from drake_rus.b import g"]


def folder_of(module: str) -> str:
    """The folder node of a module: its package under drake_rus (``drake_rus.anatomy``) or,
    for a top-level module, the module; qualified by its layer, so that a package's
    ``config`` (core) and ``cli`` (front) modules are nodes of their own."""
    parts = module.split(".")
    base = (
        ".".join(parts[:2])
        if len(parts) > 2 or (len(parts) == 2 and (ROOT / parts[1]).is_dir())
        else module
    )
    return f"{base}[{LAYERS[layer_of(module)][0]}]"


def folder_graph(graph: dict) -> dict:
    out: dict = {}
    for module, targets in graph.items():
        if module == "drake_rus":
            continue
        node = out.setdefault(folder_of(module), set())
        for target in targets:
            if target == "drake_rus" or module.startswith(target + "."):
                continue
            other = folder_of(target)
            if other != folder_of(module):
                node.add(other)
    return out


def test_no_folder_level_import_cycles():
    assert cycles(folder_graph(import_graph())) == []


def test_the_folder_checker_catches_a_cycle_between_folders():
    """anatomy.patient imports template.io and template.builder imports anatomy.rasterize:
    no module cycle, but the two folders import each other."""
    graph = {
        "drake_rus.anatomy.patient": {"drake_rus.template.io"},
        "drake_rus.anatomy.rasterize": set(),
        "drake_rus.template.io": set(),
        "drake_rus.template.builder": {"drake_rus.anatomy.rasterize"},
    }
    assert cycles(graph) == []
    assert cycles(folder_graph(graph)) == [
        ["drake_rus.anatomy[models]", "drake_rus.template[models]"]
    ]


# Tests that run the robot against the wall clock (paced at real time, or franky-sim on its
# fixed port 1337) carry the `wallclock` mark: make test runs them alone, after the others
# ran on several processes, so no test beside them slows the loop they time, and two of
# them never share a port.
WALLCLOCK_SIGNS = ("realtime_rate", "franky_sim", "FRANKY_SIM")


def unmarked_wallclock_tests(folder: Path) -> list[str]:
    """Test files in ``folder`` that show a sign of a wall-clock run but no wallclock mark."""
    return sorted(
        p.name
        for p in folder.glob("test_*.py")
        if any(sign in (text := p.read_text()) for sign in WALLCLOCK_SIGNS)
        and "pytest.mark.wallclock" not in text
    )


def test_wall_clock_tests_are_marked():
    assert unmarked_wallclock_tests(Path(__file__).resolve().parent) == []


def test_the_wallclock_check_can_fail(tmp_path):
    (tmp_path / "test_a.py").write_text("def test_x(franky_sim):\n    pass\n")
    (tmp_path / "test_b.py").write_text(
        "import pytest\npytestmark = pytest.mark.wallclock\ndef test_y(franky_sim):\n    pass\n"
    )
    assert unmarked_wallclock_tests(tmp_path) == ["test_a.py"]
