"""A stored result names the CPU its times were taken on."""

from benchmarks.provenance import cpu_model, machine_text


def test_cpu_model_is_read_from_cpuinfo(tmp_path):
    info = tmp_path / "cpuinfo"
    info.write_text("processor\t: 0\nvendor_id\t: AuthenticAMD\nmodel name\t: AMD EPYC 9B14\nflags\t: fpu\n")
    assert cpu_model(info) == "AMD EPYC 9B14"


def test_a_missing_cpuinfo_or_model_name_gives_an_empty_name(tmp_path):
    assert cpu_model(tmp_path / "absent") == ""
    (tmp_path / "cpuinfo").write_text("processor\t: 0\n")
    assert cpu_model(tmp_path / "cpuinfo") == ""


def test_machine_text_names_the_cpu_model_when_known():
    m = {"host": "vm", "cpus": 2, "cpu_model": "AMD EPYC 9B14", "platform": "Linux", "torch": "2.13"}
    assert "(AMD EPYC 9B14)" in machine_text(m)
    assert "()" not in machine_text({**m, "cpu_model": ""})
