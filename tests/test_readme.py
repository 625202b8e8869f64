"""A newcomer's first hour, run as the README writes it, in a fresh clone of this commit:
the demo's command in the background, then the first session's commands in order, each
answer checked.

The demo's first run installs Locus into ``.venv`` from the package index; here the clone
gets that environment made from the suite's own instead (this checkout's code first on
its path, the suite's installed packages after it, a ``locus`` script), so the run needs
no network and takes seconds. ``scripts/demo.sh`` sees an installed ``.venv`` and starts
at once, as it does on every run after the first. Ports are the README's unless taken:
the demo's through ``LOCUS_PORT``, the second server's by rewriting ``8001``.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import sysconfig
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from tests.conftest import free_port

ROOT = Path(__file__).resolve().parents[1]
MARK = "@@ command "
BOX_KEY = re.compile(r"Admin key\s+(\S+)")


def sh_blocks(readme: str, heading: str) -> list[str]:
    """Return the ```sh blocks of the README's section ``## heading``."""
    section = readme.split(f"\n## {heading}\n", 1)[1].split("\n## ", 1)[0]
    return re.findall(r"```sh\n(.*?)```", section, flags=re.S)


def commands(block: str) -> list[str]:
    """Return a block's commands, each with its continuation lines joined."""
    return [c for c in re.split(r"(?<!\\)\n", block) if c.strip()]


def clone_environment(clone: Path) -> None:
    """Give the clone the ``.venv`` the demo's first run would install (see the docstring)."""
    venv = clone / ".venv"
    subprocess.run(
        [Path(sys.base_prefix) / "bin" / "python3", "-m", "venv", "--without-pip", venv],
        check=True,
    )
    packages = next((venv / "lib").glob("python3*/site-packages"))
    (packages / "locus.pth").write_text(f"{clone}\n{sysconfig.get_paths()['purelib']}\n")
    script = venv / "bin" / "locus"
    # as pip writes a console script: worker processes re-import it without running it
    script.write_text(
        f"#!{venv}/bin/python\nimport sys\n\nfrom app.cli import main\n\n"
        "if __name__ == '__main__':\n    sys.exit(main())\n"
    )
    script.chmod(0o755)
    # installed after pyproject.toml last changed, as a first run leaves it
    past = time.time() - 60
    os.utime(clone / "pyproject.toml", (past, past))


def clean_env() -> dict[str, str]:
    """Return this environment without the suite's: no Locus settings, no Python path."""
    env = {
        k: v
        for k, v in os.environ.items()
        if not k.startswith("LOCUS_") and k not in ("PYTHONPATH", "VIRTUAL_ENV")
    }
    path = os.environ.get("PATH", "").split(os.pathsep)
    env["PATH"] = os.pathsep.join(p for p in path if not p.startswith(sys.prefix))
    # one filter worker per server: the demo and the second server share two cores here
    return env | {"LOCUS_WORKERS": "1"}


def stop(process: subprocess.Popen[bytes]) -> None:
    """End a process started in its own session, and everything it started."""
    if process.poll() is None:
        os.killpg(process.pid, signal.SIGTERM)
        try:
            process.wait(timeout=30)
        except subprocess.TimeoutExpired:
            os.killpg(process.pid, signal.SIGKILL)
            process.wait()


@pytest.fixture
def clone(tmp_path: Path) -> Path:
    """A fresh clone of the checkout's HEAD, with the demo's environment."""
    if shutil.which("curl") is None:
        pytest.skip("the README's commands use curl, which is not installed")
    target = tmp_path / "locus"
    subprocess.run(["git", "clone", "--quiet", str(ROOT), str(target)], check=True)
    clone_environment(target)
    return target


@pytest.fixture
def demo(clone: Path) -> Iterator[tuple[str, str, Path]]:
    """The README's demo command running in the clone; yields (dashboard URL, key, log)."""
    block = sh_blocks((clone / "README.md").read_text(), "Two commands")[0]
    port = 8000 if free_port_is(8000) else free_port()
    log = clone / "demo.log"
    process = subprocess.Popen(
        ["bash", "-c", block],
        cwd=clone,
        env=clean_env() | {"LOCUS_PORT": str(port)},
        stdout=log.open("wb"),
        stderr=subprocess.STDOUT,
        start_new_session=True,
    )
    try:
        deadline = time.monotonic() + 120
        while not BOX_KEY.search(log.read_text()):
            assert process.poll() is None, log.read_text()
            assert time.monotonic() < deadline, log.read_text()
            time.sleep(0.2)
        text = log.read_text()
        url = re.search(r"Dashboard\s+(\S+)", text)
        assert url is not None, text
        yield url.group(1), BOX_KEY.findall(text)[0], log
    finally:
        stop(process)


def free_port_is(port: int) -> bool:
    """Return whether ``port`` on loopback is free."""
    try:
        httpx.get(f"http://127.0.0.1:{port}/", timeout=0.5)
    except httpx.ConnectError:
        return True
    except httpx.HTTPError:
        pass
    return False


def test_the_readme_first_hour_runs_as_written(clone: Path, demo: tuple[str, str, Path]) -> None:
    url, key, log = demo
    # the demo: its box names a dashboard that answers and a key that signs in
    assert httpx.get(url, timeout=10).status_code == 200
    sites = httpx.get(f"{url}v1/sites", headers={"Authorization": f"Bearer {key}"}, timeout=10)
    assert sites.status_code == 200 and "demo" in sites.text
    # the box is printed last, and the devices' requests log nothing after it
    time.sleep(3)
    after_box = log.read_text().split("╰", 1)[1].splitlines()[1:]
    assert not [line for line in after_box if "/v1/ingest" in line or " INFO " in line]

    # the first session, beside the running demo
    (block,) = sh_blocks((clone / "README.md").read_text(), "A first session with the API")
    port = 8001 if free_port_is(8001) else free_port()
    steps = commands(block.replace("8001", str(port)))
    script = "".join(f"echo '{MARK}{i}'\n{c}\n" for i, c in enumerate(steps))
    # then where locus came from, and the README's way to stop the second server
    script += f"echo '{MARK}end'\ncommand -v locus\nkill %1\nwait\n"
    session = subprocess.Popen(
        ["bash", "-c", script],
        cwd=clone,
        env=clean_env(),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        start_new_session=True,
    )
    try:
        out, err = session.communicate(timeout=240)
    finally:
        stop(session)
    assert session.returncode == 0, err.decode()[-3000:]
    answers = dict(
        part.split("\n", 1) for part in out.decode().split(MARK)[1:] if "\n" in part.strip()
    )
    said = {i: answers.get(str(i), "").strip() for i in range(len(steps))}

    site = json.loads(said[_index(steps, "/v1/sites/hq -H")])
    assert (site["id"], site["name"]) == ("hq", "HQ")
    floor = json.loads(said[_index(steps, "/v1/sites/hq/floors/F1")])
    assert floor["floor_id"] == "F1" and floor["counts"]["wall"] > 0
    device_key = json.loads(said[_index(steps, "/v1/keys")])
    assert device_key["role"] == "device" and device_key["site_id"] == "hq" and device_key["key"]
    ingest = json.loads(said[_index(steps, "/v1/ingest?wait=true")])
    (position,) = ingest["positions"]
    assert (position["device_id"], position["site_id"]) == ("tag-1", "hq")
    assert (position["x"], position["y"]) == pytest.approx((12, 10), abs=0.5)
    # every other command answered nothing; locus came from the demo's environment
    assert len([text for text in said.values() if text]) == 4, said
    assert answers["end"].splitlines()[0] == str(clone / ".venv" / "bin" / "locus")


def _index(steps: list[str], text: str) -> int:
    """Return the index of the one command containing ``text``."""
    (index,) = [i for i, step in enumerate(steps) if text in step]
    return index
