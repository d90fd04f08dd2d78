"""Bad files at the user's level (issue 8, reliability item 3): ``facewire`` given hostile
``.fwm`` models and ``.fwlog`` packet logs.

Each bad file is refused by every command that reads it (``model info``, ``model export``,
``replay``, ``send``, ``receive``; ``inspect``, ``bench bandwidth`` and ``replay`` for logs)
with exit status 2 and one line on stderr that names the file and the member or field, no
traceback, and nothing written: no output file or folder, nothing in the working folder,
next to the model or in the model cache, and ``send`` / ``receive`` refuse the model before
they bind or connect a socket. Models: truncated, bit-flipped, over the size limit, a member
declaring a huge size, zip bombs (one honest about its size, one understating it), a PNG
"image bomb" (a few kB of flat 4096 x 4096 layers that decode to 300 MiB), path-traversal
member names, NaN and infinity in arrays and in the manifest, indices outside the mesh.
Logs: a truncated or bit-flipped header, over the size limit, a Hello declaring 4 GiB, not
a log at all. A log with a few damaged records (or a cut-off tail, or megabytes of zeros
between records) is not refused: those records are counted and skipped, and the rest is
replayed; a log with no intact packet, or whose times span a year, is reported by
``inspect`` and refused by ``replay``.

The matrix of cases runs ``facewire.cli.main`` in this process (the console script is
``main()``: same parsing, dispatch and error handling, at no start-up cost); a few cases
then run the real console script in a subprocess, as a user runs it.
"""

from __future__ import annotations

import io
import json
import os
import socket
import struct
import subprocess
import sys
import zipfile
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import free_endpoint, npy_bytes, write_zip, zip_members

from facewire.cli import main
from facewire.models import modelfile
from facewire.models.geometry import Intrinsics
from facewire.models.head import generic_head
from facewire.models.manifest import MAX_MEMBER_BYTES, ModelInfo
from facewire.models.modelfile import PersonModel, Region, save_model
from facewire.protocol import log as fwlog
from facewire.protocol.control import Camera as HelloCamera
from facewire.protocol.control import Hello
from facewire.protocol.log import LogWriter, read_log
from facewire.protocol.packet import FRAME_DTYPE, Flag, encode_frames

# The banner ``facewire send`` prints before ``send()`` has checked anything (facewire/cli.py).
SEND_BANNER = "facewire send: publishing on"
# The warning ``send`` and ``encode`` print once model and source are accepted when the model
# holds no face descriptors, as the generic model of these tests does (sender.pipeline).
IDENTITY_WARNING = "stores no face descriptors"


# ---- what a user sees ---------------------------------------------------------------------

def visible_lines(stderr: str) -> list[str]:
    """The non-blank lines a terminal shows: progress bars redraw with ``\\r``, so only the
    text after a line's last ``\\r`` stays on screen."""
    lines = (line.rsplit("\r", 1)[-1].strip() for line in stderr.split("\n"))
    return [line for line in lines if line]


def refusal(code: int, stderr: str, *names: str) -> str:
    """The one error line of a refused command: exit 2, no traceback, names every fragment.

    ``send``'s banner (see ``test_send_prints_only_the_refusal``) and the warning that a
    model without descriptors cannot hold its person are left out here, so that the other
    checks hold on their own.
    """
    assert code == 2, stderr
    assert "Traceback" not in stderr, stderr
    lines = [line for line in visible_lines(stderr)
             if not line.startswith(SEND_BANNER) and IDENTITY_WARNING not in line]
    assert len(lines) == 1, lines
    for name in names:
        assert name in lines[0], (name, lines[0])
    return lines[0]


def snapshot(*folders: Path) -> dict[str, tuple[int, int]]:
    """Every file and folder below ``folders``: path -> (size, mtime in ns)."""
    seen = {}
    for folder in folders:
        for path in [folder, *folder.rglob("*")]:
            st = path.lstat()
            seen[str(path)] = (st.st_size if path.is_file() else -1, st.st_mtime_ns)
    return seen


# ---- a base model, log and the bad copies ---------------------------------------------------

def base_model() -> PersonModel:
    """The generic head with one small region (so a model has templates to corrupt)."""
    rng = np.random.default_rng(8)
    region = Region("mouth", (0.4, 0.1, 0.6, 0.3), (0.45, 0.15, 0.55, 0.25),
                    layers=rng.integers(0, 256, (2, 8, 8, 3), dtype=np.uint8),
                    mask=np.full((8, 8), 255, np.uint8),
                    templates=rng.standard_normal((2, 16, 16)).astype(np.float32))
    return PersonModel(mesh=generic_head(), texture=np.full((64, 128, 3), 170, np.uint8),
                       camera=Intrinsics(640.0, 640.0, 319.5, 239.5, 640, 480),
                       info=ModelInfo(name="base"), regions=(region,))


def with_array(good: Path, bad: Path, field: str, change: Callable[[np.ndarray], None]
               ) -> None:
    """A copy of ``good`` whose ``arrays/FIELD.npy`` (or ``regions/..``) went through
    ``change``."""
    content = zip_members(good)
    name = field if "/" in field else f"arrays/{field}.npy"
    array = np.load(io.BytesIO(content[name]))
    change(array)
    content[name] = npy_bytes(array)
    write_zip(bad, content)


def local_header(data: bytes, name: str) -> int:
    """Offset of a member's local file header."""
    with zipfile.ZipFile(io.BytesIO(data)) as archive:
        return archive.getinfo(name).header_offset


def renamed(good: Path, bad: Path, evil: str) -> None:
    """A copy with one member's name replaced, byte for byte, by ``evil`` (in its local
    header and in the zip directory), as a hostile writer would store it."""
    content = zip_members(good)
    placeholder = "x" * len(evil)
    content[placeholder] = b"payload"
    write_zip(bad, content)
    data = bad.read_bytes()
    assert data.count(placeholder.encode()) == 2
    bad.write_bytes(data.replace(placeholder.encode(), evil.encode()))


def flipped(good: Path, bad: Path, member: str) -> None:
    """A copy with one bit flipped in the middle of ``member``'s stored data."""
    data = bytearray(good.read_bytes())
    at = local_header(bytes(data), member)
    name_len, extra_len = struct.unpack_from("<HH", data, at + 26)
    size = struct.unpack_from("<I", data, at + 18)[0]
    data[at + 30 + name_len + extra_len + size // 2] ^= 0x10
    bad.write_bytes(bytes(data))


def declared(good: Path, bad: Path, member: str, size: int) -> None:
    """A copy whose ``member`` declares ``size`` bytes uncompressed (local header and
    directory), its data unchanged."""
    data = bytearray(good.read_bytes())
    struct.pack_into("<I", data, local_header(bytes(data), member) + 22, size)
    central = data.index(b"PK\x01\x02")
    encoded = member.encode()
    while data[central + 46:central + 46 + len(encoded)] != encoded:
        central = data.index(b"PK\x01\x02", central + 1)
    struct.pack_into("<I", data, central + 24, size)
    bad.write_bytes(bytes(data))


def bomb(good: Path, bad: Path, member: str, inflated: int, declare: int | None = None
         ) -> None:
    """A copy whose ``member`` is ``inflated`` zero bytes, deflated (about 1000:1); with
    ``declare``, it claims to inflate to that many bytes only."""
    content = zip_members(good)
    content[member] = bytes(inflated)
    write_zip(bad, content)
    if declare is not None:
        declared(bad, bad, member, declare)


def image_bomb(good: Path, bad: Path, k: int = 6) -> None:
    """A copy whose region holds ``k`` flat 4096 x 4096 layers: each a few kB of PNG, 48 MiB
    decoded, 300 MiB in all."""
    content = {n: d for n, d in zip_members(good).items() if not n.startswith("regions/mouth/")}
    manifest = json.loads(content["model.json"])
    manifest["members"] = {n: e for n, e in manifest["members"].items()
                           if not n.startswith("regions/mouth/")}
    side = 4096
    layer = png(np.full((side, side, 3), 90, np.uint8))
    for j in range(k):
        content[f"regions/mouth/layer_{j:02d}.png"] = layer
        manifest["members"][f"regions/mouth/layer_{j:02d}.png"] = {
            "dtype": "uint8", "shape": [side, side, 3]}
    content["regions/mouth/mask.png"] = png(np.full((side, side), 255, np.uint8))
    content["regions/mouth/templates.npy"] = npy_bytes(np.zeros((k, 16, 16), np.float32))
    manifest["members"]["regions/mouth/mask.png"] = {"dtype": "uint8", "shape": [side, side]}
    manifest["members"]["regions/mouth/templates.npy"] = {"dtype": "float32",
                                                          "shape": [k, 16, 16]}
    manifest["regions"][0].update(layers=k, opacity=[1.0] * k, rest=0.0)
    content["model.json"] = json.dumps(manifest).encode()
    write_zip(bad, content)


def png(image: np.ndarray) -> bytes:
    return cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, 9])[1].tobytes()


def sparse(path: Path, size: int) -> None:
    """A file of ``size`` bytes that takes no disk space (a hole)."""
    with open(path, "wb") as f:
        f.truncate(size)


def manifest_edit(good: Path, bad: Path, old: str, new: str) -> None:
    content = zip_members(good)
    text = content["model.json"].decode()
    assert old in text
    content["model.json"] = text.replace(old, new, 1).encode()
    write_zip(bad, content)


# case -> (make the bad file from the good one, fragments the error line must hold)
MODEL_CASES: dict[str, tuple[Callable[[Path, Path], None], tuple[str, ...]]] = {
    "truncated": (lambda g, b: b.write_bytes(g.read_bytes()[:g.stat().st_size // 2]),
                  ("truncated",)),
    "truncated-end-record": (lambda g, b: b.write_bytes(g.read_bytes()[:-1]), ("truncated",)),
    "bit-flip-vertices": (lambda g, b: flipped(g, b, "arrays/vertices.npy"),
                          ("arrays/vertices.npy", "CRC")),
    "bit-flip-texture": (lambda g, b: flipped(g, b, "textures/neutral.png"),
                         ("textures/neutral.png", "CRC")),
    "oversized-file": (lambda g, b: sparse(b, modelfile.MAX_FILE_BYTES + 1),
                       ("more than the 268435456",)),
    "member-declares-huge-size": (
        lambda g, b: declared(g, b, "arrays/uv.npy", MAX_MEMBER_BYTES + 1),
        ("arrays/uv.npy", "declares 67108865 bytes")),
    "zip-bomb": (lambda g, b: bomb(g, b, "arrays/vertices.npy", 16 << 20),
                 ("arrays/vertices.npy", "zip bomb")),
    "zip-bomb-understated": (lambda g, b: bomb(g, b, "arrays/vertices.npy", 16 << 20, 4096),
                             ("arrays/vertices.npy", "corrupt")),
    "image-bomb": (image_bomb, ("model.json", "members", "more than the 268435456")),
    "traversal-dotdot": (lambda g, b: renamed(g, b, "../evil"), ("'../evil'", "unsafe name")),
    "traversal-absolute": (lambda g, b: renamed(g, b, "/abs"), ("'/abs'", "unsafe name")),
    "traversal-inner": (lambda g, b: renamed(g, b, "a/../../b"),
                        ("'a/../../b'", "unsafe name")),
    "nan-vertices": (lambda g, b: with_array(g, b, "vertices",
                                             lambda a: a.__setitem__((7, 1), np.nan)),
                     ("mesh: vertices", "NaN")),
    "inf-uv": (lambda g, b: with_array(g, b, "uv", lambda a: a.__setitem__((3, 0), np.inf)),
               ("mesh: uv", "infinity")),
    "nan-templates": (lambda g, b: with_array(g, b, "regions/mouth/templates.npy",
                                              lambda a: a.__setitem__((1, 2, 3), np.nan)),
                      ("region 'mouth'", "templates", "NaN")),
    "inf-camera": (lambda g, b: manifest_edit(g, b, '"fx": 640.0', '"fx": 1e999'),
                   ("model.json", "camera.fx", "finite")),
    "triangle-outside-mesh": (lambda g, b: with_array(g, b, "triangles",
                                                      lambda a: a.__setitem__((5, 2), 11236)),
                              ("mesh: triangles", "outside [0, 11236)")),
    "landmark-outside-mesh": (lambda g, b: with_array(g, b, "landmarks",
                                                      lambda a: a.__setitem__(30, -1)),
                              ("mesh: landmarks", "outside [0, 11236)")),
}


@pytest.fixture(scope="module")
def files(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """The good model, a log made with it, and every bad model (one folder, read only)."""
    folder = tmp_path_factory.mktemp("bad_models")
    good = folder / "good.fwm"
    sha = save_model(base_model(), good)
    out = {"good": good, "log": session_log(folder / "good.fwlog", sha, good.stat().st_size)}
    for case, (make, _) in MODEL_CASES.items():
        make(good, folder / f"{case}.fwm")
        out[case] = folder / f"{case}.fwm"
    for path in folder.iterdir():
        path.chmod(0o444)
    return out


def session_log(path: Path, sha256: str, size: int, n: int = 30) -> Path:
    """A 1 s, 30 Hz log of a frontal face for the model ``sha256``."""
    frames = np.zeros(n, FRAME_DTYPE)
    frames["seq"] = np.arange(n)
    frames["flags"] = Flag.FACE_PRESENT
    frames["translation"] = (0, 0, -650)
    packets, _ = encode_frames(frames)
    hello = Hello(sha256, size, 30.0, HelloCamera(640.0, 640.0, 319.5, 239.5, 640, 480),
                  ("mouth",))
    with LogWriter(path, hello) as writer:
        for i, packet in enumerate(packets):
            writer.write(packet.tobytes(), 1_700_000_000.0 + i / 30)
    return path


# ---- bad models -------------------------------------------------------------------------------

def model_commands(model: Path, log: Path, out: Path, port: int) -> dict[str, list[str]]:
    endpoint = f"tcp://127.0.0.1:{port}"
    return {
        "model info": ["model", "info", str(model)],
        "model export": ["model", "export", str(model), "-o", str(out / "head.glb")],
        "replay to a folder": ["replay", str(log), "--model", str(model), "--out",
                               str(out / "frames")],
        "replay to mp4": ["replay", str(log), "--model", str(model), "--out",
                          str(out / "video.mp4")],
        # the port is held by the test: a send that bound before checking the model would
        # fail on it instead
        "send": ["send", "--model", str(model), "--source", "camera:0", "--bind", endpoint],
        "receive": ["receive", "--model", str(model), "--connect", endpoint, "--idle-timeout",
                    "1", "--frames", str(out / "received")],
    }


@pytest.mark.parametrize("case", MODEL_CASES)
def test_bad_model_is_refused_by_every_command(case: str, files: dict[str, Path], work: Path,
                                               capfd: pytest.CaptureFixture[str]) -> None:
    bad, fragments = files[case], MODEL_CASES[case][1]
    out = work / "out"
    out.mkdir()
    with socket.socket() as held:
        held.bind(("127.0.0.1", 0))
        held.listen()
        held.setblocking(False)
        port = held.getsockname()[1]
        before = snapshot(work, bad.parent)
        for command, argv in model_commands(bad, files["log"], out, port).items():
            code = main(argv)
            line = refusal(code, capfd.readouterr().err, str(bad), *fragments)
            assert snapshot(work, bad.parent) == before, (command, line)
        # receive refused the model before it connected: nothing knocked on the port
        with pytest.raises(BlockingIOError):
            held.accept()


def test_send_prints_only_the_refusal(files: dict[str, Path], work: Path) -> None:
    """``facewire send`` with a bad model says one thing: why it is refused.

    Fails while facewire/cli.py prints "publishing on ..." before ``send()`` has loaded
    the model and bound the socket (it never publishes).
    """
    done = run_cli("send", "--model", str(files["truncated"]), "--source", "camera:0",
                   "--bind", free_endpoint(), cwd=work / "cwd")
    refusal(done.returncode, done.stderr, str(files["truncated"]))
    assert visible_lines(done.stderr) == [visible_lines(done.stderr)[-1]], done.stderr


def run_cli(*args: str, cwd: Path, timeout: float = 120) -> subprocess.CompletedProcess[str]:
    """The real command, as a user runs it."""
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1",
           "FACEWIRE_CACHE": str(cwd.parent / "cache")}
    return subprocess.run([sys.executable, "-m", "facewire.cli", *args], capture_output=True,
                          text=True, timeout=timeout, cwd=cwd, env=env)


@pytest.mark.parametrize("case, command", [("bit-flip-vertices", "replay to a folder"),
                                           ("traversal-dotdot", "model info"),
                                           ("zip-bomb", "receive")])
def test_the_console_script_refuses_a_bad_model_in_one_line(
        case: str, command: str, files: dict[str, Path], work: Path) -> None:
    out = work / "out"
    out.mkdir()
    before = snapshot(work, files[case].parent)
    argv = model_commands(files[case], files["log"], out, 9)[command]
    done = run_cli(*argv, cwd=work / "cwd")
    refusal(done.returncode, done.stderr, str(files[case]), *MODEL_CASES[case][1])
    assert done.stdout == ""
    assert snapshot(work, files[case].parent) == before


def test_the_good_model_is_accepted(files: dict[str, Path], work: Path,
                                    capfd: pytest.CaptureFixture[str]) -> None:
    """The matrix above fails for the bad part of each file, not for its base."""
    assert main(["model", "info", str(files["good"]), "--json"]) == 0
    summary = json.loads(capfd.readouterr().out.strip().splitlines()[-1])
    assert summary["regions"] == 1 and summary["vertices"] == 11236


# ---- bad logs ----------------------------------------------------------------------------------

def flip_header(good: Path, bad: Path) -> None:
    data = bytearray(good.read_bytes())
    data[20] ^= 0x01  # inside the Hello: the header's CRC-32 no longer matches
    bad.write_bytes(bytes(data))


LOG_CASES: dict[str, tuple[Callable[[Path, Path], None], tuple[str, ...]]] = {
    "truncated-header": (lambda g, b: b.write_bytes(g.read_bytes()[:40]),
                         ("header", "truncated")),
    "bit-flip-header": (flip_header, ("header.crc", "corrupt")),
    "oversized": (lambda g, b: sparse(b, fwlog.MAX_LOG_BYTES + 1),
                  ("larger than the 2147483648",)),
    "hello-declares-4-GiB": (lambda g, b: b.write_bytes(g.read_bytes()[:12] + b"\xff" * 4
                                                        + g.read_bytes()[16:]),
                             ("header.hello_length", "4294967295 exceeds")),
    "not-a-log": (lambda g, b: b.write_bytes(b"PK\x03\x04" + bytes(200)),
                  ("header.magic", "not a facewire packet log")),
}


@pytest.mark.parametrize("case", LOG_CASES)
def test_bad_log_is_refused_by_every_command(case: str, files: dict[str, Path], work: Path,
                                             capfd: pytest.CaptureFixture[str]) -> None:
    bad = work / f"{case}.fwlog"
    LOG_CASES[case][0](files["log"], bad)
    out = work / "out"
    out.mkdir()
    before = snapshot(work)
    for argv in (["inspect", str(bad), "--csv", str(out / "frames.csv")],
                 ["bench", "bandwidth", "--log", str(bad), "--plot", str(out / "bw.png")],
                 ["replay", str(bad), "--model", str(files["good"]), "--out",
                  str(out / "frames")],
                 ["replay", str(bad), "--model", str(files["good"]), "--out",
                  str(out / "video.mp4")]):
        code = main(argv)
        refusal(code, capfd.readouterr().err, str(bad), *LOG_CASES[case][1])
        assert snapshot(work) == before, argv


def test_the_console_script_refuses_a_bad_log_in_one_line(files: dict[str, Path],
                                                          work: Path) -> None:
    bad = work / "flipped.fwlog"
    flip_header(files["log"], bad)
    before = snapshot(work)
    done = run_cli("replay", str(bad), "--model", str(files["good"]), "--out",
                   str(work / "out.mp4"), cwd=work / "cwd")
    refusal(done.returncode, done.stderr, str(bad), "header.crc")
    assert snapshot(work) == before


def damage_records(good: Path, bad: Path, records: list[int], cut: int) -> None:
    """A copy of ``good`` with one byte changed in each of ``records`` and the last record
    cut ``cut`` bytes short."""
    data = bytearray(good.read_bytes())
    start = len(data) - len(read_log(good).packets) * fwlog.RECORD_BYTES
    for k in records:
        data[start + k * fwlog.RECORD_BYTES + 20] ^= 0xFF
    bad.write_bytes(bytes(data[:len(data) - cut]))


def test_damaged_records_are_counted_and_skipped_and_the_rest_replayed(
        files: dict[str, Path], work: Path) -> None:
    bad = work / "damaged.fwlog"
    damage_records(files["log"], bad, [4, 11, 12], cut=9)  # 3 corrupt, the last one cut off
    done = run_cli("replay", str(bad), "--model", str(files["good"]), "--out",
                   str(work / "frames"), "--size", "64x48", "--json", cwd=work / "cwd")
    assert done.returncode == 0, done.stderr
    assert "Traceback" not in done.stderr
    summary = json.loads(done.stdout.strip().splitlines()[-1])
    assert summary["lost_records"] == 4
    assert "4 damaged log records" in done.stdout
    # slots 0 .. 28 are played (the cut-off 29th is gone); the 3 damaged ones concealed
    assert summary["frames"] == 29 == len(list((work / "frames").glob("frame_*.png")))
    assert summary["concealed"] == 3 and summary["received"] == 26
    assert sorted(p.name for p in work.iterdir()) == ["cwd", "damaged.fwlog", "frames"]
    assert not any((work / "cwd").iterdir())

    done = run_cli("inspect", str(bad), "--json", cwd=work / "cwd")
    assert done.returncode == 0, done.stderr
    assert "lost or corrupt records: 4" in done.stdout
    assert json.loads(done.stdout.strip().splitlines()[-1])["frames"] == 26


def log_with_times(good: Path, bad: Path, times: list[float]) -> None:
    """A copy of ``good`` keeping its first ``len(times)`` packets, recorded at ``times``."""
    log = read_log(good)
    with LogWriter(bad, log.hello) as writer:
        for packet, t in zip(log.packets, times):
            writer.write(packet.tobytes(), t)


# case -> (make it, what replay's error line holds); inspect and bench bandwidth read them
NOTHING_TO_REPLAY: dict[str, tuple[Callable[[Path, Path], None], tuple[str, ...]]] = {
    "every-record-corrupt": (lambda g, b: damage_records(g, b, list(range(30)), cut=0),
                             ("no intact packet", "30 damaged records")),
    "no-records": (lambda g, b: log_with_times(g, b, []), ("no intact packet",)),
    "times-span-a-year": (lambda g, b: log_with_times(g, b, [1.7e9, 1.7e9 + 3.2e7]),
                          ("times", "span")),
}


@pytest.mark.parametrize("case", NOTHING_TO_REPLAY)
def test_a_log_with_nothing_to_replay_is_reported_and_refused_by_replay(
        case: str, files: dict[str, Path], work: Path,
        capfd: pytest.CaptureFixture[str]) -> None:
    bad = work / f"{case}.fwlog"
    NOTHING_TO_REPLAY[case][0](files["log"], bad)
    lost = read_log(bad).lost
    assert main(["inspect", str(bad)]) == 0
    assert f"lost or corrupt records: {lost}" in capfd.readouterr().out
    before = snapshot(work)
    for out in ("frames", "video.mp4"):
        code = main(["replay", str(bad), "--model", str(files["good"]), "--out",
                     str(work / out), "--size", "64x48"])
        refusal(code, capfd.readouterr().err, str(bad), *NOTHING_TO_REPLAY[case][1])
        assert snapshot(work) == before, out


def test_a_zero_filled_hole_in_a_log_is_skipped_quickly(files: dict[str, Path],
                                                       work: Path) -> None:
    """64 MiB of zeros between records (blocks a crash left unwritten): counted as lost and
    read in well under a minute (a byte-by-byte search took 3 s a MiB)."""
    data = files["log"].read_bytes()
    start = len(data) - 30 * fwlog.RECORD_BYTES
    hole = 64 << 20
    bad = work / "hole.fwlog"
    with open(bad, "wb") as f:
        f.write(data[:start + 10 * fwlog.RECORD_BYTES])
        f.seek(hole, os.SEEK_CUR)  # a sparse hole: zeros, no disk space
        f.write(data[start + 10 * fwlog.RECORD_BYTES:])
    done = run_cli("inspect", str(bad), "--json", cwd=work / "cwd", timeout=60)
    assert done.returncode == 0, done.stderr
    summary = json.loads(done.stdout.strip().splitlines()[-1])
    assert summary["frames"] == 30
    assert summary["lost_records"] == round(hole / fwlog.RECORD_BYTES)
