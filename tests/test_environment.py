"""torchslam.environment: the machine described from /proc/cpuinfo."""

import builtins
import io

from torchslam import environment

CPUINFO = """processor\t: 0
vendor_id\t: AuthenticAMD
model name\t: AMD EPYC 7B13
flags\t\t: fpu sse2 avx2
vmx flags\t: ept

processor\t: 1
model name\t: a second CPU
"""


def test_cpuinfo_field_reads_the_first_line_of_that_key(monkeypatch):
    real_open = builtins.open
    monkeypatch.setattr(builtins, "open", lambda path, *a, **k: io.StringIO(CPUINFO) if path == "/proc/cpuinfo"
                        else real_open(path, *a, **k))
    assert environment.cpuinfo_field("model name") == "AMD EPYC 7B13"
    assert environment.cpuinfo_field("flags") == "fpu sse2 avx2"  # not "vmx flags"
    assert environment.cpuinfo_field("cache size") is None
    assert environment.cpu_model() == "AMD EPYC 7B13"


def test_without_cpuinfo_the_model_comes_from_platform(monkeypatch):
    def missing(*a, **k):
        raise FileNotFoundError("/proc/cpuinfo")

    monkeypatch.setattr(builtins, "open", missing)
    assert environment.cpuinfo_field("model name") is None
    monkeypatch.setattr(environment.platform, "processor", lambda: "arm64")
    assert environment.cpu_model() == "arm64"
