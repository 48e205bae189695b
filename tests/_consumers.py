"""The real consumers of ``macsec export``, run on what it wrote (Debian's packages, .ci/apt-packages).

- wpa_supplicant (``wpasupplicant``): ``-dd`` in a private network and mount namespace
  (``unshare -mn``, a tmpfs on /run), driver ``macsec_linux`` on ``lo``. It reads the whole
  file before the driver starts, then fails for want of kernel MACsec; the exit code is 255
  either way, so the log is read: a "Line N: ..." error or "Failed to read or parse
  configuration" is a refusal, and every ``network={`` must have been started.
- systemd-networkd (``systemd``): its own parser, the files under a private
  /run/systemd/network (``unshare -mn``), installed as the docs say (root:systemd-network
  0640); read until "Enumeration completed", then stopped. Any line naming our file is a
  complaint ("Unknown key", "Invalid", "ignoring", "too permissive"); each .netdev must log
  ``NAME: loaded "macsec"``.
- iproute2: ``bash -n`` on the script; then its ``ip`` lines as an ``ip -batch`` file in a
  private network namespace with the parent link as a veth (this kernel has no dummy). Where it has no
  MACsec, ``ip link add ... type macsec`` can only fail in the kernel ("Unknown device type",
  after iproute2 parsed every argument) and ``ip macsec`` cannot start (no "macsec" generic
  netlink family): the result says so and how far the check went.
Each ``*_unavailable()`` returns ``None`` where its consumer can run here, else the reason it cannot.
"""

from __future__ import annotations

import functools
import os
import re
import shlex
import shutil
import subprocess
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

NETWORKD = Path("/lib/systemd/systemd-networkd")
# keys wpa_supplicant 2.11 added (Debian 12's 2.10 refuses a file holding any of them)
WPA_211_KEYS = ("macsec_csindex", "macsec_offload", "macsec_icv_indicator")


@functools.cache
def _unshare_mn() -> str | None:
    if os.geteuid() != 0:
        return "private network and mount namespaces need root"
    if shutil.which("unshare") is None:
        return "unshare (util-linux) is not installed"
    probe = subprocess.run(
        ["unshare", "-mn", "sh", "-c", "mount -t tmpfs tmpfs /run"], capture_output=True, text=True, timeout=30
    )
    if probe.returncode != 0:
        return f"cannot make private network and mount namespaces here: {probe.stderr.strip()}"
    return None


@functools.cache
def wpa_supplicant_unavailable() -> str | None:
    if shutil.which("wpa_supplicant") is None:
        return "wpa_supplicant (Debian wpasupplicant) is not installed"
    return _unshare_mn()


@functools.cache
def wpa_supplicant_version() -> tuple[int, int]:
    out = subprocess.run(["wpa_supplicant", "-v"], capture_output=True, text=True, timeout=30).stdout
    m = re.search(r"wpa_supplicant v(\d+)\.(\d+)", out)
    assert m, out
    return int(m[1]), int(m[2])


def networkd_unavailable() -> str | None:
    if not NETWORKD.exists():
        return f"systemd-networkd is not installed ({NETWORKD})"
    return _unshare_mn()


def iproute2_unavailable() -> str | None:
    if shutil.which("ip") is None or shutil.which("bash") is None:
        return "iproute2 or bash is not installed"
    return _unshare_mn()


def wpa_supplicant_log(conf: Path) -> str:
    script = 'mount -t tmpfs tmpfs /run && exec timeout 20 wpa_supplicant -dd -D macsec_linux -i lo -c "$1"'
    proc = subprocess.run(
        ["unshare", "-mn", "sh", "-c", script, "sh", str(conf)], capture_output=True, text=True, timeout=60
    )
    return proc.stdout + proc.stderr


def wpa_supplicant_errors(conf: Path) -> list[str]:
    """What wpa_supplicant said was wrong with ``conf`` (empty: it read every block)."""
    log = wpa_supplicant_log(conf)
    errors = [line for line in log.splitlines() if re.match(r"Line \d+: ", line)]
    if "Failed to read or parse configuration" in log:
        errors.append("Failed to read or parse configuration")
    if f"Reading configuration file '{conf}'" not in log:
        errors.append(f"the file was not read: {log[-2000:]}")
    blocks = conf.read_text().count("network={")
    started = len(re.findall(r"^Line: \d+ - start of a new network block$", log, re.M))
    if not errors and started != blocks:
        errors.append(f"{started} network blocks read, {blocks} written")
    return errors


def networkd_log(files: list[Path]) -> str:
    """systemd-networkd's debug log up to the end of its start (the files loaded), then stopped."""
    with tempfile.TemporaryDirectory() as stage:
        for f in files:
            dst = Path(stage, f.name)
            shutil.copyfile(f, dst)
            shutil.chown(dst, "root", "systemd-network")
            dst.chmod(0o640)
        os.chmod(stage, 0o755)
        script = (
            # networkd reads as systemd-network: the folders must not follow a 077 umask of the test process
            "umask 022 && mount -t tmpfs -o mode=0755 tmpfs /run/systemd && mkdir -p /run/systemd/network "
            '&& cp -p "$1"/* /run/systemd/network/ '
            f"&& exec env SYSTEMD_LOG_LEVEL=debug SYSTEMD_LOG_TARGET=console {NETWORKD}"
        )
        proc = subprocess.Popen(
            ["unshare", "-mn", "sh", "-c", script, "sh", stage],
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        lines: list[str] = []
        deadline = time.monotonic() + 60
        try:
            assert proc.stdout is not None
            for line in proc.stdout:
                lines.append(line.rstrip("\n"))
                if "Enumeration completed" in line or time.monotonic() > deadline:
                    break
        finally:
            proc.terminate()
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        return "\n".join(lines)


def networkd_errors(files: list[Path]) -> list[str]:
    """What systemd-networkd said about ``files`` (empty: every .netdev loaded, no complaint)."""
    log = networkd_log(files)
    if "Enumeration completed" not in log:
        return [f"systemd-networkd did not finish starting: {log[-3000:]}"]
    names = {f.name for f in files}
    errors = [line for line in log.splitlines() if any(f"/run/systemd/network/{n}" in line for n in names)]
    for f in files:
        if f.suffix == ".netdev":
            m = re.search(r"^Name=(\S+)$", f.read_text(), re.M)
            assert m, f
            if f'{m[1]}: loaded "macsec"' not in log:
                errors.append(f"{f.name}: {m[1]} was not loaded")
    return errors


@dataclass
class IpResult:
    errors: list[str] = field(default_factory=list)  # what bash or iproute2 refused
    kernel: str | None = None  # why the kernel stopped the check short, if it did


def _batch(script: Path) -> tuple[list[str], list[str]]:
    """The script's ``ip`` commands as ``ip -batch`` lines, and any other command (an error)."""
    batch, other = [], []
    for line in script.read_text().splitlines():
        stripped = line.strip()
        if not stripped or stripped.startswith("#") or stripped == "set -eu":
            continue
        words = shlex.split(stripped)
        if words[0] == "ip":
            batch.append(shlex.join(words[1:]))
        else:
            other.append(stripped)
    return batch, other


def _in_netns(parents: set[str], commands: str) -> subprocess.CompletedProcess[str]:
    """``commands`` in a new network namespace whose ``parents`` exist (veth: this kernel has no dummy)."""
    setup = [f"ip link add {shlex.quote(p)} type veth peer name hcdfp{i}" for i, p in enumerate(sorted(parents))]
    setup += [f"ip link set {shlex.quote(p)} up" for p in sorted(parents)]
    script = " && ".join([*setup, commands])
    return subprocess.run(["unshare", "-n", "sh", "-c", script], capture_output=True, text=True, timeout=60)


NO_KERNEL_MACSEC = (
    "this kernel has no MACsec (CONFIG_MACSEC unset, no macsec module): `ip link add ... type macsec` was "
    "parsed by iproute2 and refused by the kernel (Unknown device type), and `ip macsec` cannot run without "
    "the macsec generic netlink family, so its lines were checked by bash -n only"
)


def iproute2_check(script: Path) -> IpResult:
    """``bash -n``, then ``ip -batch`` of its ``ip`` lines as far as the kernel allows."""
    result = IpResult()
    syntax = subprocess.run(["bash", "-n", str(script)], capture_output=True, text=True, timeout=30)
    if syntax.returncode != 0:
        result.errors.append(f"bash -n: {syntax.stderr.strip()}")
    batch, other = _batch(script)
    result.errors += [f"not an ip command: {line}" for line in other]
    parents = {b.split()[3] for b in batch if b.startswith("link add link ")}
    if not parents:
        result.errors.append("no `ip link add link PARENT ... type macsec` line")
        return result
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp, "batch")
        os.chmod(tmp, 0o755)
        probe = _in_netns(parents, f"ip link add link {shlex.quote(min(parents))} hcdfprobe type macsec")
        if probe.returncode == 0:  # a kernel with MACsec: the whole script must run
            path.write_text("\n".join(batch) + "\n")
            proc = _in_netns(parents, f"ip -batch {shlex.quote(str(path))}")
            if proc.returncode != 0 or proc.stdout.strip() or proc.stderr.strip():
                result.errors.append(f"ip -batch: {(proc.stdout + proc.stderr).strip()}")
            return result
        if "Unknown device type" not in probe.stderr:
            result.errors.append(f"probing kernel MACsec: {probe.stderr.strip()}")
            return result
        result.kernel = NO_KERNEL_MACSEC
        # without it: every `ip link` line is parsed; each may fail only in the kernel
        links = [b for b in batch if b.startswith("link ")]
        path.write_text("\n".join(links) + "\n")
        proc = _in_netns(parents, f"ip -force -batch {shlex.quote(str(path))}")
    created = {b.split()[4] for b in links if b.startswith("link add link ")}
    allowed = ["Error: Unknown device type.", *(f'Cannot find device "{d}"' for d in created)]
    for line in (proc.stdout + proc.stderr).splitlines():
        if line not in allowed and not re.fullmatch(r"Command failed .*:\d+", line):
            result.errors.append(f"ip -batch: {line}")
    if proc.returncode not in (0, 1, 2):  # 255: iproute2 refused an argument and stopped
        result.errors.append(f"ip -batch exited {proc.returncode}")
    return result


# --- every export of the suite ---


def _target(conf: Path) -> tuple[int, int]:
    m = re.search(r"^# For wpa_supplicant (\d+)\.(\d+):", conf.read_text(), re.M)
    assert m, f"{conf}: no header line naming the wpa_supplicant version it was written for"
    return int(m[1]), int(m[2])


def check_wpa_supplicant(conf: Path) -> None:
    """Debian's wpa_supplicant reads ``conf``; a file written for a newer version than the one
    installed is refused only for that version's keys, and read once they are taken out."""
    target = _target(conf)
    if target <= wpa_supplicant_version():
        errors = wpa_supplicant_errors(conf)
        assert not errors, f"wpa_supplicant {wpa_supplicant_version()} refuses {conf}: {errors}"
        return
    text = conf.read_text()
    newer = [line for line in text.splitlines() if line.strip().split("=")[0] in WPA_211_KEYS]
    assert newer, f"{conf} is written for {target} but has none of the keys 2.10 lacks"
    with tempfile.TemporaryDirectory() as tmp:
        older = Path(tmp, conf.name)
        older.write_text("\n".join(line for line in text.splitlines() if line not in newer) + "\n")
        errors = wpa_supplicant_errors(older)
    assert not errors, f"wpa_supplicant refuses {conf} without its {target} keys: {errors}"


def check_export(argv: list[str]) -> None:
    """After a successful ``hcdf-trust macsec export ARGV``: each consumer that can run here
    reads what was written (the dedicated tests in test_macsec_export.py say when one cannot)."""

    def value(flag: str) -> str | None:
        for i, a in enumerate(argv):
            if a == flag and i + 1 < len(argv):
                return argv[i + 1]
            if a.startswith(flag + "="):
                return a[len(flag) + 1 :]
        return None

    fmt, out = value("--format"), value("--out")
    if out is None or not Path(out).is_dir():
        return
    files = sorted(Path(out).iterdir())
    if fmt == "wpa_supplicant" and wpa_supplicant_unavailable() is None:
        for conf in files:
            if conf.suffix == ".conf":
                check_wpa_supplicant(conf)
    elif fmt == "networkd" and networkd_unavailable() is None:
        units = [f for f in files if f.suffix in (".netdev", ".network")]
        errors = networkd_errors(units)
        assert not errors, f"systemd-networkd complains about {out}: {errors}"
    elif fmt == "iproute2" and iproute2_unavailable() is None:
        for script in files:
            errors = iproute2_check(script).errors
            assert not errors, f"{script}: {errors}"
