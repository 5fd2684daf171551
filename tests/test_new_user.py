"""Issue 32, a new user's path: the README's commands after the README's set-up (an extra
named in one line where one is needed), ``template build`` never over the shipped model and
files 0644, the notebooks extra, the committed diagram pictures current, one tissue colour
map with a legend in every picture of tissues, servers on 127.0.0.1 only."""

import hashlib
import os
import re
import shlex
import shutil
import socket
import stat
import struct
import subprocess
import sys
import tomllib
from importlib.util import find_spec
from pathlib import Path
from types import SimpleNamespace

import matplotlib
import numpy as np
import pytest

from drake_rus.anatomy.labels import Label
from drake_rus.anatomy.tissue_colors import (
    KIDNEY_COLOR,
    MASK_ALPHA,
    NO_IMAGE_COLOR,
    TISSUE_COLORS,
    TISSUE_NAMES,
    label_image,
    labels_present,
    rgb,
)
from drake_rus.cli import build_parser, main
from drake_rus.extras import EXTRAS, MissingExtra, require
from drake_rus.paths import REPO_ROOT
from drake_rus.template.io import DEFAULT_TEMPLATE_PATH

matplotlib.use("Agg")
PYPROJECT = tomllib.loads((REPO_ROOT / "pyproject.toml").read_text())
README = (REPO_ROOT / "README.md").read_text()


# ------------------------------------------------------------------ the README's commands
DOC_PAGES = [REPO_ROOT / "README.md", *sorted((REPO_ROOT / "docs").glob("*.md"))]


def shown_commands(text: str) -> list[str]:
    """The command lines of the fenced code blocks of a Markdown page (comments and
    [optional] parts removed, ``nice``/``sudo`` and ``.venv/bin/`` dropped, continuation
    lines joined)."""
    out, fenced, pending = [], False, ""
    for line in text.splitlines():
        if line.startswith("```"):
            fenced, pending = not fenced, ""
            continue
        if not fenced:
            continue
        text = pending + " " + re.sub(r"\s+#.*$", "", line).strip()
        pending = ""
        if text.endswith("\\"):
            pending = text[:-1]
            continue
        text = re.sub(r"\s+\[[^\]]*\]", "", text).strip()
        text = re.sub(r"^(nice|sudo)\s+", "", text).replace(".venv/bin/", "")
        text = re.sub(r"\s*>\s*\S+$", "", text)  # > bench.log
        if text.startswith(("drake-rus ", "python -m ", "pip ", "make ")):
            out.append(text)
    return out


def test_every_command_the_docs_show_parses():
    """Each ``drake-rus ...`` line the README and docs/ show is a valid command line (a
    renamed command or flag fails here), each ``python -m X`` names a module that exists,
    each extra exists, and no ``template build`` shown writes over the shipped template."""
    from drake_rus.template.cli import check_not_shipped

    commands = [c for page in DOC_PAGES for c in shown_commands(page.read_text())]
    assert sum(c.startswith("drake-rus ") for c in commands) >= 20
    parser = build_parser()
    benchmarks = [p.stem for p in (REPO_ROOT / "benchmarks").glob("[a-z]*.py")]
    for command in commands:
        argv = ["2" if a == "N" else a for a in shlex.split(command)]  # a placeholder
        if argv[0] == "drake-rus":
            try:
                args = parser.parse_args(argv[1:])
            except SystemExit:
                pytest.fail(f"shown command does not parse: {command}")
            if argv[1:3] == ["template", "build"] and args.out is not None:
                check_not_shipped(REPO_ROOT / args.out, args.png)
        elif argv[0] == "python" and argv[2] == "benchmarks":
            assert argv[3] in benchmarks + ["all"], command
        elif argv[0] == "python":
            assert find_spec(argv[2]) is not None, command
        elif argv[0] == "pip":
            extra = re.search(r"\.\[(\w+)\]", command).group(1)
            assert extra in PYPROJECT["project"]["optional-dependencies"], command


def test_rehearse_without_opencv_names_the_extra(tmp_path, capsys, monkeypatch):
    """The base install (make demo) has no OpenCV: rehearse and the stop drill say in one
    line which extra installs it, exit status 2, and write nothing."""
    monkeypatch.setitem(sys.modules, "cv2", None)  # import cv2 -> ImportError
    assert main(["rehearse", "--out", str(tmp_path / "r"), "--netns", "no"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    assert "OpenCV" in err and "pip install -e '.[hardware]'" in err, err
    from drake_rus.rehearsal.drill import main as drill

    assert drill(["--out", str(tmp_path / "d")]) == 2
    assert "pip install -e '.[hardware]'" in capsys.readouterr().err
    assert not (tmp_path / "r").exists() and not (tmp_path / "d").exists()


@pytest.mark.parametrize("module", sorted(EXTRAS))
def test_each_optional_module_names_an_extra_that_exists(module, monkeypatch):
    extra = EXTRAS[module][0]
    assert extra in PYPROJECT["project"]["optional-dependencies"]
    monkeypatch.setitem(sys.modules, module, None)
    with pytest.raises(MissingExtra, match=re.escape(f"pip install -e '.[{extra}]'")) as e:
        require(module, "this command")
    assert isinstance(e.value, ValueError) and isinstance(e.value, ImportError)


# ------------------------------------------------------------------ template build
def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_template_build_defaults_to_a_user_path():
    from drake_rus.template.cli import DEFAULT_BUILD_OUT

    args = build_parser().parse_args(["template", "build"])
    assert args.out is None  # generated kidneys: DEFAULT_BUILD_OUT; --from-ct: cache
    out = DEFAULT_BUILD_OUT
    assert not out.is_absolute() and out.parts[0] == "runs" and out.suffix == ".npz"
    assert (REPO_ROOT / out).resolve() != DEFAULT_TEMPLATE_PATH.resolve()


@pytest.mark.parametrize(
    "flags,arg",
    [
        (["--out", str(DEFAULT_TEMPLATE_PATH)], "--out"),
        (
            ["--out", str(DEFAULT_TEMPLATE_PATH.parent / ".." / "models" / "kidney_template.npz")],
            "--out",
        ),
        (
            [
                "--out",
                "OUT",
                "--png",
                str(DEFAULT_TEMPLATE_PATH.with_name("kidney_template_convergence.png")),
            ],
            "--png",
        ),
    ],
)
def test_template_build_never_writes_over_the_shipped_model(flags, arg, tmp_path, capsys):
    shipped = {p: _digest(p) for p in DEFAULT_TEMPLATE_PATH.parent.glob("kidney_template*")}
    flags = [str(tmp_path / "t.npz") if f == "OUT" else f for f in flags]
    assert main(["template", "build", "--n", "2", *flags]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"drake-rus template: error: {arg}: ") and "shipped" in err, err
    assert err.count("\n") == 1
    assert {p: _digest(p) for p in shipped} == shipped
    assert not list(tmp_path.iterdir())


def test_template_build_writes_every_file_0644(tmp_path, capsys):
    """save_template and the metadata JSON went through mkstemp (0600) without a chmod."""
    umask = os.umask(0o022)
    os.umask(umask)
    out = tmp_path / "t.npz"
    assert (
        main(
            [
                "template",
                "build",
                "--n",
                "3",
                "--points",
                "300",
                "--voxel-mm",
                "2",
                "--out",
                str(out),
                "--quiet",
            ]
        )
        == 0
    )
    assert str(out.resolve()) in capsys.readouterr().out  # how to use it
    written = sorted(tmp_path.iterdir())
    assert [p.name for p in written] == ["t.json", "t.npz", "t_convergence.png", "t_modes.png"]
    for p in written:
        assert stat.S_IMODE(p.stat().st_mode) == 0o666 & ~umask, p


# ------------------------------------------------------------------ notebooks
def test_notebooks_extra_and_make_target():
    extra = PYPROJECT["project"]["optional-dependencies"]["notebooks"]
    assert any(r.startswith("jupyterlab") for r in extra)
    assert any(r.startswith("ipykernel") for r in extra)
    if shutil.which("make") is None:
        pytest.skip("make is not installed")
    dry = subprocess.run(
        ["make", "-n", "-C", str(REPO_ROOT), "notebooks", "VENV=/nonexistent/venv"],
        capture_output=True,
        text=True,
        check=True,
    )
    # Installed through the set-up's pip wrapper (it says the disk it needs; see
    # tests/test_install_script.py).
    assert re.search(
        r"scripts/pip_install\.sh /nonexistent/venv \d+ .*-e '\.\[notebooks\]'", dry.stdout
    ), dry.stdout
    assert re.search(r"jupyter lab --ip=127\.0\.0\.1 .*notebooks/", dry.stdout), dry.stdout
    assert "make notebooks" in README


# ------------------------------------------------------------------ diagram pictures
needs_graphviz = pytest.mark.skipif(
    shutil.which("dot") is None, reason="Graphviz 'dot' is not installed"
)


@needs_graphviz
def test_committed_diagram_pictures_are_current():
    """The systems and ports in diagrams/*.svg are those of the diagrams built now; re-draw
    with `drake-rus render-diagram --all` (make diagrams) when this fails."""
    from drake_rus.render import COMMITTED, committed_picture_drift

    assert set(COMMITTED) == {p.name for p in (REPO_ROOT / "diagrams").glob("*.svg")}
    for name in COMMITTED:
        missing, extra = committed_picture_drift(name)
        assert not missing and not extra, (
            f"diagrams/{name} is stale: lacks {sorted(missing)}, shows {sorted(extra)} in "
            f"excess; run drake-rus render-diagram --all"
        )


@needs_graphviz
def test_a_stale_picture_is_found(tmp_path, monkeypatch):
    import drake_rus.render as render

    svg = (REPO_ROOT / "diagrams" / "station.svg").read_text()
    hold = re.search(r"<text[^>]*>name=command_hold</text>", svg)
    assert hold is not None
    (tmp_path / "station.svg").write_text(svg.replace(hold.group(0), ""))
    monkeypatch.setattr(render, "DIAGRAMS_DIR", tmp_path)
    missing, extra = render.committed_picture_drift("station.svg")
    assert set(missing) == {"name=command_hold"} and not extra


# ------------------------------------------------------------------ tissue colours
def _colours(image) -> set:
    a = np.asarray(image, float)
    if a.max() > 1.0:
        a = a / 255.0
    return {tuple(c) for c in np.round(a[..., :3].reshape(-1, 3), 3)}


def _map_colours(*extra) -> set:
    return {tuple(np.round(rgb(c), 3)) for c in [*TISSUE_COLORS.values(), *extra]}


def _legend_texts(fig) -> set:
    return {t.get_text() for leg in fig.findobj(matplotlib.legend.Legend) for t in leg.get_texts()}


def _capture(monkeypatch, module) -> list:
    figures = []

    def keep(fig, path, dpi=110):
        figures.append(fig)
        return Path(path)

    monkeypatch.setattr(module, "save_figure", keep)
    return figures


def test_one_colour_per_tissue():
    assert set(TISSUE_COLORS) == set(Label) == set(TISSUE_NAMES)
    assert len(set(TISSUE_COLORS.values())) == len(Label)
    labels = np.array([[int(v) for v in Label] + [200]], np.uint8)
    image = label_image(labels, where=np.r_[np.ones(len(Label), bool), True][None, :])
    for k, label in enumerate(Label):
        np.testing.assert_allclose(image[0, k], rgb(TISSUE_COLORS[label]))
    np.testing.assert_allclose(image[0, -1], (1.0, 0.0, 1.0))  # unknown label: magenta
    outside = label_image(labels, where=np.zeros(labels.shape, bool))
    np.testing.assert_allclose(outside[0, 0], rgb(NO_IMAGE_COLOR))


def test_start_plan_picture_has_the_tissue_legend_and_explains_the_marks(monkeypatch):
    from test_start_planner import X_BPT, box_body

    import drake_rus.scan.planning as planning
    from drake_rus.imaging.config import ImagingConfig
    from drake_rus.scan.config import StartConfig

    plan = planning.PlanStart(box_body(blocker=Label.BONE), X_BPT, ImagingConfig(), StartConfig())
    figures = _capture(monkeypatch, planning)
    planning.plot_start_plan(plan, ImagingConfig(), "unused.png")
    fig = figures[0]
    image = fig.axes[0].get_images()[0].get_array()
    assert _colours(image) <= _map_colours()
    texts = _legend_texts(fig)
    present = labels_present(plan.plane[0])
    assert Label.BONE in present and Label.KIDNEY_CORTEX in present
    assert {TISSUE_NAMES[label] for label in present} <= texts
    assert any(t.startswith("bone or gas shadowing the kidney") for t in texts), texts
    assert any(t.startswith("rejected windows") for t in texts), texts


def test_label_slices_use_the_tissue_map(monkeypatch):
    import drake_rus.anatomy.pictures as pictures
    from drake_rus.anatomy.generator import generate_patient

    figures = _capture(monkeypatch, pictures)
    pictures.plot_label_slices(generate_patient(8, voxel_size=0.004, progress=False), "x.png")
    fig = figures[0]
    for ax in fig.axes:
        assert _colours(ax.get_images()[0].get_array()) <= _map_colours()
    assert {"kidney cortex", "fat", "muscle", "bone"} <= _legend_texts(fig)


def test_pivot_frames_show_the_mask_in_the_kidney_colour(monkeypatch):
    import drake_rus.scan.report as report

    grey = np.full((40, 50), 100, np.uint8)
    mask = np.zeros_like(grey, bool)
    mask[10:20, 10:30] = True
    figures = _capture(monkeypatch, report)
    report.plot_frames(SimpleNamespace(images=[(1.0, grey, mask), (2.0, grey, mask)]), "x.png")
    fig = figures[0]
    shown = fig.axes[0].get_images()[0].get_array()
    expected = (1 - MASK_ALPHA) * 100 / 255 + MASK_ALPHA * np.array(rgb(KIDNEY_COLOR))
    np.testing.assert_allclose(shown[15, 15], expected)
    np.testing.assert_allclose(shown[0, 0], [100 / 255] * 3)
    assert "kidney: the segmenter's mask" in _legend_texts(fig)


def test_every_phase_swatch_shows():
    """traces.png's legend: DONE was white on white (a blank swatch)."""
    from drake_rus.control.supervisor import Phase
    from drake_rus.scan.report import PHASE_COLORS

    assert {p.name for p in Phase} <= set(PHASE_COLORS)
    colours = [c.lower() for c in PHASE_COLORS.values()]
    assert "#ffffff" not in colours and len(set(colours)) == len(colours)


def test_imaging_pictures_use_the_tissue_map(tmp_path, monkeypatch):
    import drake_rus.imaging.cli as icli

    figures = _capture(monkeypatch, icli)
    assert (
        main(
            [
                "imaging-pictures",
                "--patient",
                "phantom:1",
                "--views",
                "0",
                "--segmenter",
                "oracle",
                "--out",
                str(tmp_path),
            ]
        )
        == 0
    )
    view = figures[0]
    assert _colours(view.axes[0].get_images()[0].get_array()) <= _map_colours(NO_IMAGE_COLOR)
    texts = _legend_texts(view)
    assert {"kidney cortex", "kidney: the segmenter's mask", "kidney: true outline"} <= texts
    assert "kidney: the segmenter's mask" in _legend_texts(figures[-1])  # contact sheet


# ------------------------------------------------------------------ servers
def _socket_inodes() -> set:
    inodes = set()
    for fd in os.listdir("/proc/self/fd"):
        try:
            target = os.readlink(f"/proc/self/fd/{fd}")
        except OSError:
            continue
        if target.startswith("socket:["):
            inodes.add(target[8:-1])
    return inodes


def listening_addresses(port: int) -> list[str]:
    """The local addresses this process listens on at TCP ``port`` (Linux /proc/net)."""
    mine, out = _socket_inodes(), []
    for table, v6 in (("/proc/net/tcp", False), ("/proc/net/tcp6", True)):
        try:
            rows = Path(table).read_text().splitlines()[1:]
        except OSError:
            continue
        for row in rows:
            f = row.split()
            address, port_hex = f[1].split(":")
            if f[3] != "0A" or int(port_hex, 16) != port or f[9] not in mine:
                continue
            words = [
                struct.pack("<I", int(address[i : i + 8], 16)) for i in range(0, len(address), 8)
            ]
            out.append(socket.inet_ntop(socket.AF_INET6 if v6 else socket.AF_INET, b"".join(words)))
    return out


needs_proc = pytest.mark.skipif(not Path("/proc/net/tcp").exists(), reason="needs Linux /proc")


@needs_proc
def test_meshcat_listens_on_the_loopback_only():
    """Drake's default Meshcat host "*" listens on every interface."""
    from drake_rus.cli import MakeMeshcat

    meshcat = MakeMeshcat()
    assert listening_addresses(meshcat.port()) == ["127.0.0.1"]
    assert "127.0.0.1" in meshcat.web_url()


@needs_proc
def test_rehearsal_video_listens_on_the_loopback_only():
    from drake_rus.rehearsal.mjpeg import FrameBuffer, MjpegServer

    with MjpegServer(FrameBuffer()) as server:
        assert listening_addresses(server.port) == ["127.0.0.1"]
    for host in ("localhost", "0.0.0.0", "::1"):
        with pytest.raises(ValueError, match="127.0.0.1"):
            MjpegServer(FrameBuffer(), host=host)


def test_no_server_is_made_outside_the_loopback_helpers():
    """Every Meshcat goes through MakeMeshcat (127.0.0.1) and every HTTP server binds a
    checked host: the product and the notebooks are read for other constructors."""
    sources = [p for p in (REPO_ROOT / "drake_rus").rglob("*.py")]
    sources += list((REPO_ROOT / "notebooks").glob("*.ipynb"))
    offenders = []
    for path in sources:
        text = path.read_text()
        for m in re.finditer(
            r"\b(StartMeshcat|Meshcat|(?:Threading)?HTTPServer|TCPServer)\(", text
        ):
            offenders.append(f"{path.relative_to(REPO_ROOT)}: {m.group(0)}")
    assert sorted(offenders) == [
        "drake_rus/cli.py: Meshcat(",
        "drake_rus/rehearsal/mjpeg.py: ThreadingHTTPServer(",
    ], offenders
