"""Faults around run files and the ``nhsde`` command: no silent wrong number, no hang, no lost work.

A damaged, truncated or edited partial file (its data, coordinates or
attributes) is refused naming it (or, where the damage missed everything a
resume reads, resumes bitwise); a second writer is refused; output paths are
checked before any work and links are never written through; a full disk or
the file-size limit keeps the pieces written, with one line and exit status 1; resume compares the package's
sources, not the git revision; limits of the TOML are refused naming the key;
the command ends bad input with one line and exit status 2.
"""

import copy
import errno
import io
import json
import os
import re
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import xarray as xr
from hypothesis import HealthCheck, given, settings, strategies as st
from test_runs import BASE, BASE_TOML

import nhsde
from nhsde.runs import ConfigError, RunConfig, checksum, load_config, load_run, main, run, source_hash

CONFIG = RunConfig.from_dict(BASE)  # 300 paths in 5 pieces of 64, paths kept


class Stop(Exception):
    pass


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """The uninterrupted run, and a partial file of its first two pieces."""
    folder = tmp_path_factory.mktemp("runs")
    whole = run(CONFIG, folder / "whole.nc")

    def stop(k):
        if k == 1:
            raise Stop

    with pytest.raises(Stop):
        run(CONFIG, folder / "partial.nc", on_piece=stop)
    return whole, folder / "partial.nc"


def resumed_or_refused(path: Path, whole: xr.Dataset) -> str:
    """Resume ``path``: 'refused' naming it, or 'same' (bitwise the uninterrupted result); anything else fails."""
    try:
        ds = run(CONFIG, path)
    except ConfigError as e:
        assert str(path) in str(e), str(e)
        return "refused"
    for name in whole.data_vars:
        np.testing.assert_array_equal(ds[name].values, whole[name].values, err_msg=name)
    return "same"


def test_damaged_partial_files_are_refused_or_resume_bitwise(runs, tmp_path):
    whole, partial = runs
    data = partial.read_bytes()
    ds = load_run(partial)
    stored = [ds[v].values.tobytes() for v in ("piece_sum_z", "piece_sum_zzzz")]
    stored += [b'"seed": 5', ds.attrs["source"].encode()]
    assert all(data.count(b) == 1 for b in stored)
    targets = [data.find(b) + len(b) - 5 for b in stored]  # in the last number or the last characters
    offsets = [*np.linspace(0, len(data) - 1, 12).astype(int), *targets]
    outcomes = {}
    for offset in offsets:
        damaged = bytearray(data)
        damaged[offset] ^= 0x5A
        path = tmp_path / f"flip{offset}.nc"
        path.write_bytes(damaged)
        outcomes[offset] = resumed_or_refused(path, whole)
    assert all(outcomes[t] == "refused" for t in targets), outcomes  # the stored numbers and text: the checksum
    for size in (0, 100, len(data) // 2, len(data) - 1):
        path = tmp_path / f"cut{size}.nc"
        path.write_bytes(data[:size])
        assert resumed_or_refused(path, whole) == "refused", size
    path = tmp_path / "intact.nc"
    shutil.copy(partial, path)
    assert resumed_or_refused(path, whole) == "same"


def test_edited_partial_files_are_refused(runs, tmp_path):
    """piece_n_used = 10**9 in a 300-path run: the checksum no longer matches; resealed, the counts are impossible."""
    whole, partial = runs
    path = tmp_path / "edited.nc"
    ds = load_run(partial)
    ds["piece_n_used"].values[1] = 10**9
    ds.to_netcdf(path, engine="h5netcdf")
    with pytest.raises(ConfigError, match=f"{re.escape(str(path))} is damaged or was edited"):
        run(CONFIG, path)
    ds.attrs["checksum"] = checksum(ds)
    ds.to_netcdf(path, engine="h5netcdf")
    with pytest.raises(ConfigError, match=f"{re.escape(str(path))}: impossible counts"):
        run(CONFIG, path)


@pytest.mark.parametrize(
    "edit",
    [
        lambda ds: ds.assign_coords(time=ds["time"].values * 2),
        lambda ds: ds.assign_coords(name=["y", "u_x"]),
        lambda ds: ds.assign_coords(role=("name", ["velocity", "position"])),
    ],
    ids=["time", "name", "role"],
)
def test_edited_coordinates_are_refused(runs, tmp_path, edit):
    """The checksum covers the coordinates: an edited time or name is refused, like an edited number."""
    whole, partial = runs
    path = tmp_path / "edited.nc"
    stored = load_run(partial)
    edited = edit(stored)
    assert not edited.identical(stored) and edited.attrs == stored.attrs
    edited.to_netcdf(path, engine="h5netcdf")
    refusal = f"{re.escape(str(path))} is damaged or was edited: its contents .*coordinates.* do not match"
    with pytest.raises(ConfigError, match=refusal):
        load_run(path)
    with pytest.raises(ConfigError, match=refusal):
        run(CONFIG, path)


def test_a_file_of_an_earlier_format_is_refused_naming_its_version(runs, tmp_path):
    _, partial = runs
    path = tmp_path / "old.nc"
    ds = load_run(partial)
    ds.attrs["format_version"] = 2  # its checksum, of format version 3, no longer matches: as a version-2 file's
    ds.to_netcdf(path, engine="h5netcdf")
    with pytest.raises(ConfigError, match=f"{re.escape(str(path))} is of format version 2, whose checksum"):
        load_run(path)


def test_a_second_writer_is_refused(runs, tmp_path):
    whole, _ = runs
    out = tmp_path / "run.nc"
    refusal = f"{re.escape(str(out))} is being written by another process"

    def second_writer(k):
        if k == 0:
            with pytest.raises(ConfigError, match=refusal):
                run(CONFIG, out)

    run(CONFIG, out, on_piece=second_writer)
    assert not (tmp_path / "run.nc.lock").exists()

    out.unlink()
    lock = tmp_path / "run.nc.lock"
    holder = subprocess.Popen(
        [sys.executable, "-c", "import fcntl, sys, time; f = open(sys.argv[1], 'w'); fcntl.flock(f, fcntl.LOCK_EX); "
         "print(flush=True); time.sleep(60)", str(lock)],
        stdout=subprocess.PIPE,
    )  # fmt: skip
    try:
        assert holder.stdout is not None
        holder.stdout.readline()
        with pytest.raises(ConfigError, match=refusal):
            run(CONFIG, out)
        assert not out.exists()
    finally:
        holder.kill()
        holder.wait()
    np.testing.assert_array_equal(run(CONFIG, out)["cov"].values, whole["cov"].values)  # its lock left behind: taken
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.nc"]


def test_output_paths_are_checked_before_any_work(tmp_path, capsys):
    def no_work(k):
        raise AssertionError("started before the output was checked")

    notes = tmp_path / "notes.txt"
    notes.write_text("not a run file")
    foreign = tmp_path / "foreign.nc"
    xr.Dataset({"a": ("x", np.arange(3.0))}).to_netcdf(foreign, engine="h5netcdf")
    link = tmp_path / "link.nc"
    link.symlink_to(notes)
    cases = [
        (tmp_path, "is a directory"),
        (tmp_path / "missing" / "run.nc", "the directory .* does not exist"),
        (notes, "cannot be read as netCDF"),
        (foreign, "is not an nhsde run file"),
        (link, "is not a regular file"),
    ]
    for out, message in cases:
        with pytest.raises(ConfigError, match=f"{re.escape(str(out))}:? .*{message}"):
            run(CONFIG, out, on_start=no_work)
    (tmp_path / "run.nc.lock").symlink_to(notes)
    with pytest.raises(ConfigError, match="cannot create its lock file"):
        run(CONFIG, tmp_path / "run.nc", on_start=no_work)
    assert notes.read_text() == "not a run file"
    if os.geteuid() != 0:  # root writes anywhere
        locked = tmp_path / "locked"
        locked.mkdir(mode=0o500)
        with pytest.raises(ConfigError, match="cannot write in the directory"):
            run(CONFIG, locked / "run.nc", on_start=no_work)

    # the command: `simulate SCENE --out` (refused before it prints its plan), `fit --out` (before reading the data)
    fit = tmp_path / "fit.toml"
    fit.write_text(
        'scene = "ball-on-vibrating-plane"\n[solver]\ndt = 0.05\n[paths]\nn = 64\n[fit]\ndata = "missing.nc"\n'
    )
    assert main(["simulate", "ball-on-vibrating-plane", "--out", str(notes)]) == 2
    out, err = capsys.readouterr()
    assert out == "" and f"{notes}: cannot be read as netCDF" in err
    assert notes.read_text() == "not a run file"
    (tmp_path / "fit.nc").mkdir()
    assert main(["fit", "--config", str(fit), "--out", str(tmp_path / "fit.nc")]) == 2
    assert f"{tmp_path / 'fit.nc'} is a directory" in capsys.readouterr().err


def test_a_link_at_the_temporary_name_is_replaced_not_followed(runs, tmp_path):
    whole, _ = runs
    victim = tmp_path / "victim.txt"
    victim.write_text("keep me")
    (tmp_path / "run.nc.partial").symlink_to(victim)
    np.testing.assert_array_equal(run(CONFIG, tmp_path / "run.nc")["mean"].values, whole["mean"].values)
    assert victim.read_text() == "keep me"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.nc", "victim.txt"]


def test_a_full_disk_keeps_the_pieces_written(runs, tmp_path, monkeypatch, capsys):
    """The third write fails at its sync with ENOSPC: the file keeps two pieces, the command says so, resume is
    bitwise."""
    whole, _ = runs
    cfg = tmp_path / "run.toml"
    cfg.write_text(BASE_TOML)
    out = tmp_path / "run.nc"
    fsync, calls = os.fsync, []

    def full_disk_on_the_third(fd):
        calls.append(fd)
        if len(calls) == 3:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return fsync(fd)

    monkeypatch.setattr(os, "fsync", full_disk_on_the_third)
    assert main(["simulate", "--config", str(cfg), "--no-progress"]) == 1
    err = capsys.readouterr().err
    assert re.fullmatch(f"nhsde simulate: .*cannot write {re.escape(str(out))} \\(No space left on device\\).*\n", err)
    monkeypatch.undo()
    assert load_run(out).attrs["pieces_done"] == 2
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.nc", "run.toml"]
    assert resumed_or_refused(out, whole) == "same"


FILE_SIZE_LIMIT = """
import resource, signal, sys
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # the write fails with EFBIG instead of killing the process
limit = int(sys.argv[1])
resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
from nhsde.runs import main
sys.exit(main(["simulate", "--config", sys.argv[2], "--out", sys.argv[3], "--no-progress"]))
"""


def test_the_file_size_limit_ends_with_one_line_and_the_file_intact(runs, tmp_path):
    """Resumed under a file-size limit of the partial file's size, the next write fails (EFBIG): one line, exit 1,
    no signal (no crash as the HDF5 handle is freed), the two pieces written still load and resume bitwise."""
    whole, partial = runs
    out = tmp_path / "run.nc"
    shutil.copy(partial, out)
    before = out.read_bytes()
    cfg = tmp_path / "run.toml"
    cfg.write_text(BASE_TOML)
    child = subprocess.run(
        [sys.executable, "-c", FILE_SIZE_LIMIT, str(len(before)), str(cfg), str(out)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert child.returncode == 1, (
        signal.Signals(-child.returncode) if child.returncode < 0 else child.returncode,
        child.stderr,
    )
    assert child.stderr == f"nhsde simulate: cannot write {out} (File too large); it keeps what it held before\n"
    assert out.read_bytes() == before and load_run(out).attrs["pieces_done"] == 2
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.nc", "run.toml"]
    assert resumed_or_refused(out, whole) == "same"


def test_resume_compares_the_sources_not_the_git_revision(runs, tmp_path):
    """A file started at another commit (or from a tree dirty then) resumes; one started from other sources does not."""
    whole, partial = runs
    for key, value in [("git_revision", "0" * 40 + "+dirty"), ("source", "f" * 64)]:
        ds = load_run(partial)
        ds.attrs[key] = value
        ds.attrs["checksum"] = checksum(ds)
        ds.to_netcdf(tmp_path / f"{key}.nc", engine="h5netcdf")
    assert resumed_or_refused(tmp_path / "git_revision.nc", whole) == "same"
    with pytest.raises(ConfigError, match="source.nc was started with source f{64}, now [0-9a-f]{64}"):
        run(CONFIG, tmp_path / "source.nc")


def test_the_source_hash_covers_the_package_python_files_only(tmp_path):
    package = tmp_path / "nhsde"
    shutil.copytree(Path(nhsde.__file__).parent, package, ignore=shutil.ignore_patterns("__pycache__"))
    before = source_hash(package)
    assert before == source_hash()  # the installed package's, as imported
    (package / "README.md").write_text("documentation")
    assert source_hash(package) == before
    with open(package / "_simulate.py", "a") as f:
        f.write("\n# a changed line\n")
    assert source_hash(package) != before


@pytest.mark.parametrize(
    "old, new, message",
    [
        ("n = 300", "n = 9223372036854775807", "paths.n = 9223372036854775807: must be ≤ 2147483647"),
        ("n = 300", "n = 2147483648", "paths.n = 2147483648: must be ≤ 2147483647"),
        ("n = 300", "n = 65", "paths.n = 65: the last piece of paths.chunk = 64 would hold 1 paths"),
        ("chunk = 64", "chunk = 4294967296", "paths.chunk = 4294967296: must be ≤ 2147483648"),
        ("seed = 5", "seed = 18446744073709551615", "seed = 18446744073709551615: must be ≤ 9223372036854775807"),
        ("t1 = 1.0", "t1 = 1e300", "solver.t1 = 1e\\+300: .* steps per path, beyond the budget of 10000000"),
        ("dt = 0.05", "dt = 1e-8", "solver.t1 = 1.0: .* = 1e\\+08 steps per path, beyond the budget"),
        ("t1 = 1.0", "t0 = -1.7e308\nt1 = 1.7e308", "solver.t1 = 1.7e\\+308: .* = inf steps"),
        ("t1 = 1.0", "t1 = 1e400", "solver.t1 = inf: must be finite"),
        ("dt = 0.05", "dt = 1" + "0" * 400, "solver.dt = 1000.*: must be finite"),
        ("save_points = 5", "save_points = 100000000000000000000", "statistics.save_points = .*: beyond the 64-bit"),
        ("save_points = 5", "save_points = 1" + "0" * 5000, "run.toml: not valid TOML: Exceeds the limit"),
        ("n = 300", "n = " + "[" * 5000 + "]" * 5000, "run.toml: not valid TOML: nested too deeply"),
        ("n = 300", "n = " + "{a = " * 2000 + "1" + "}" * 2000, "run.toml: not valid TOML: nested too deeply"),
        ('save = ["x", "u_x"]', 'save = ["x", "u_x", "y", "u_y", "q", "r", "s", "t", "u"]', "'q' is not offered"),
        ("eps = 0.8", 'eps = "0.8"', "parameters.eps: expected a number, got a string '0.8'"),
        (
            'scene = "ball-on-vibrating-plane"',
            'scene = "body-on-vibrating-plane"\noptions = {body = "sphere"}',
            "options.body: unknown option of body-on-vibrating-plane; options: friction, drift",
        ),
    ],
)
def test_run_file_limits_are_refused_naming_the_key(tmp_path, capsys, old, new, message):
    cfg = tmp_path / "run.toml"
    cfg.write_text(BASE_TOML.replace(old, new, 1))
    with pytest.raises(ConfigError, match=message):
        load_config(cfg)
    assert main(["simulate", "--config", str(cfg)]) == 2
    err = capsys.readouterr().err
    assert len(err) < 500 and re.fullmatch(f"nhsde simulate: {re.escape(str(cfg))}: .*\n", err), err


def test_files_that_are_not_run_files_are_refused_naming_them(tmp_path):
    binary = tmp_path / "binary.toml"
    binary.write_bytes(BASE_TOML.encode() + b"\xff\xfe\x00")
    big = tmp_path / "big.toml"
    big.write_text(BASE_TOML + "#" * 2**21)
    fifo = tmp_path / "fifo.toml"
    os.mkfifo(fifo)  # reading it would wait for a writer
    for path, message in [
        (binary, "not a text file \\(byte \\d+ is not UTF-8\\)"),
        (big, "not a regular file of at most 1048576 bytes"),
        (fifo, "not a regular file"),
        (tmp_path, "not a regular file"),
    ]:
        with pytest.raises(ConfigError, match=f"{re.escape(str(path))}: {message}"):
            load_config(path)


def test_the_command_exits_2_with_one_line_for_a_binary_config(tmp_path):
    cfg = tmp_path / "run.toml"
    cfg.write_bytes(b"\x89PNG\r\n\x1a\n\x00\x00")
    result = subprocess.run(
        [sys.executable, "-m", "nhsde.runs", "simulate", "--config", str(cfg)], capture_output=True, text=True
    )
    assert result.returncode == 2 and result.stdout == "" and "Traceback" not in result.stderr
    assert result.stderr.splitlines()[-1] == f"nhsde simulate: {cfg}: not a text file (byte 0 is not UTF-8)."


def test_progress_is_shown_by_default_on_a_terminal(tmp_path, monkeypatch):
    class Terminal(io.StringIO):
        def isatty(self):
            return True

    cfg = tmp_path / "run.toml"
    cfg.write_text(BASE_TOML.replace("n = 300", "n = 64"))
    for argv, terminal, shown in [([], True, True), (["--no-progress"], True, False), ([], False, False)]:
        monkeypatch.setattr(sys, "stderr", Terminal() if terminal else io.StringIO())
        out = tmp_path / f"{len(argv)}{terminal}.nc"
        assert main(["simulate", "--config", str(cfg), "--out", str(out), *argv]) == 0
        assert ("100.00%" in sys.stderr.getvalue()) == shown, sys.stderr.getvalue()


def test_the_command_says_what_it_will_run_and_roughly_how_long(runs, tmp_path, capsys):
    cfg = tmp_path / "run.toml"
    long_run = BASE_TOML.replace("n = 300", "n = 4096").replace("chunk = 64", "chunk = 4096")
    cfg.write_text(long_run.replace("t1 = 1.0", "t1 = 5.0"))
    out = tmp_path / "result.txt"
    assert main(["simulate", "--config", str(cfg), "--no-progress", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert f"{out}: 4096 paths × 100 steps (euler, dt = 0.05), roughly " in text
    assert "of it compiling (an estimate from a timed pilot of 4096 paths × 20 steps) in pieces of 4096" in text
    assert f"saved {out} (netCDF, although the name does not end in .nc)" in text
    assert sorted(p.name for p in tmp_path.iterdir()) == ["result.txt", "run.toml"]

    _, partial = runs
    shutil.copy(partial, tmp_path / "partial.nc")
    cfg.write_text(BASE_TOML)
    assert main(["simulate", "--config", str(cfg), "--no-progress", "--out", str(tmp_path / "partial.nc")]) == 0
    text = capsys.readouterr().out
    assert "partial.nc: 172 paths × 20 steps (euler, dt = 0.05) in pieces of 64; resuming: 2 of 5 pieces" in text
    assert "piece 3 written" in text and "piece 2 written" not in text


# ---- fuzzing the run file ------------------------------------------------------------------------

BASE_DOC = {
    "": {"scene": '"ball-on-vibrating-plane"', "seed": "5"},
    "parameters": {"eps": "0.8", "nu": "1.5"},
    "solver": {"name": '"euler"', "dt": "0.05", "t1": "1.0"},
    "paths": {"n": "300", "chunk": "64"},
    "statistics": {"save": '["x", "u_x"]', "save_points": "5", "keep_paths": "true"},
}
KEYS = {  # the keys of each table, with some it does not have
    "": ["scene", "seed", "precision", "colour"],
    "options": ["drift", "angular_velocity", "route", "spin"],
    "parameters": ["eps", "nu", "radius", "mass"],
    "initial_state": ["x", "u_x", "z"],
    "solver": ["name", "dt", "t0", "t1", "rtol"],
    "paths": ["n", "chunk"],
    "statistics": ["save", "save_points", "keep_paths"],
}
QUOTED = st.text(max_size=6).map(lambda s: json.dumps(s, ensure_ascii=False))  # a TOML basic string
LITERALS = st.one_of(
    st.sampled_from(
        [
            '"euler"',
            '"sra1"',
            '"float32"',
            '"rolling-disk"',
            '"chaplygin-sleigh"',
            '"body-on-vibrating-plane"',
            '"reduced"',
            "true",
            "false",
            "0",
            "-1",
            "4",
            "64",
            "300",
            "0.05",
            "1e300",
            "1e400",
            "-inf",
            "nan",
            "9223372036854775807",
            "99999999999999999999",
            "0x7fffffff",
            "1979-05-27T07:32:00Z",
            "{a = 1}",
            '["x", "u_x"]',
            '["x", "x"]',
            "[]",
            "[1, 2]",
            "[[[[1]]]]",
            '\'__import__("os").system("true")\'',
        ]
    ),  # fmt: skip
    st.integers(-(2**70), 2**70).map(str),
    st.floats().map(lambda x: repr(x) if np.isfinite(x) else str(x)),
    QUOTED,
    st.lists(st.sampled_from(['"x"', '"y"', '"u_x"', '"q"', "1", "1.5"]), max_size=5).map(", ".join).map("[{}]".format),
)


def render(doc: dict) -> str:
    lines = [f"{k} = {v}" for k, v in doc.get("", {}).items()]
    for table, items in doc.items():
        lines += [f"[{table}]", *(f"{k} = {v}" for k, v in items.items())] if table else []
    return "\n".join(lines) + "\n"


@st.composite
def run_files(draw) -> bytes:
    """The base run file with keys set, added or removed, sometimes with bytes cut or spliced in."""
    doc = copy.deepcopy(BASE_DOC)
    for _ in range(draw(st.integers(1, 3))):
        table = draw(st.sampled_from(sorted(KEYS)))
        key = draw(QUOTED if draw(st.integers(0, 5)) == 0 else st.sampled_from(KEYS[table]))
        if draw(st.integers(0, 4)) == 0:
            doc.get(table, {}).pop(key, None)
        else:
            doc.setdefault(table, {})[key] = draw(LITERALS)
    text = render(doc).encode()
    if draw(st.integers(0, 4)) == 0:
        i = draw(st.integers(0, len(text)))
        text = text[:i] + draw(st.binary(max_size=4)) + text[i + draw(st.integers(0, 4)) :]
    return text


@pytest.fixture(scope="module")
def fuzz_file(tmp_path_factory):
    return tmp_path_factory.mktemp("fuzz") / "run.toml"


@settings(max_examples=150, deadline=5_000, derandomize=True, suppress_health_check=[HealthCheck.too_slow])
@given(text=run_files())
def test_fuzzed_run_files_load_or_name_the_key(fuzz_file, text):
    """``load_config`` returns a configuration (which round-trips) or raises ConfigError naming the key or the file."""
    fuzz_file.write_bytes(text)
    try:
        config = load_config(fuzz_file)
    except ConfigError as e:
        assert str(e).startswith(f"{fuzz_file}: "), str(e)
        if e.key is None:
            assert re.search("not valid TOML|not a text file", str(e)), str(e)
        else:
            assert e.key in str(e), (e.key, str(e))
        return
    assert RunConfig.from_dict(json.loads(config.to_json())).data == config.data
