"""``hostlink export-ground`` as a user runs it, and the XTCE document against the protocol table (without openc3:
these run in the oldest-versions lane too, where yamcs-pymdb writes the XTCE at its lower bound)."""

from __future__ import annotations

import xml.etree.ElementTree as ET

from emulator_fixtures import hostlink

from hostlink.portkit import export_ground
from protocol.messages import MAX_STARS, MESSAGES

XTCE_NS = {"x": "http://www.omg.org/spec/XTCE/20180204"}


def test_export_ground_writes_every_file_and_refuses_a_file_as_dir(tmp_path):
    run = hostlink("export-ground", str(tmp_path / "g"))
    assert run.returncode == 0, run.stderr
    assert run.stdout.split() == [str(tmp_path / "g" / f) for f in export_ground.FILES]
    (tmp_path / "file").write_text("x")
    bad = hostlink("export-ground", str(tmp_path / "file"))
    assert bad.returncode != 0 and len(bad.stderr.strip().splitlines()) == 1 and "not a directory" in bad.stderr
    under_a_file = hostlink("export-ground", str(tmp_path / "file" / "sub"))
    assert under_a_file.returncode == 2 and "cannot write" in under_a_file.stderr
    assert len(under_a_file.stderr.strip().splitlines()) == 1
    assert "export-ground" in hostlink("--help").stdout


def test_the_xtce_has_a_container_or_command_with_every_field_of_every_message(tmp_path):
    export_ground.write_ground(tmp_path)
    root = ET.parse(tmp_path / export_ground.XTCE_FILE).getroot()
    containers = {c.get("name"): c for c in root.iter(f"{{{XTCE_NS['x']}}}SequenceContainer")}
    commands = {c.get("name"): c for c in root.iter(f"{{{XTCE_NS['x']}}}MetaCommand")}
    for spec in MESSAGES:
        records = {f.name for f in spec.fields if f.fmt == "record"}
        # a length field is folded into the field it sizes (a leading size); a record's star count stays
        folded = {f.name for f in spec.fields if f.length_of and f.length_of not in records}
        names = []
        for f in spec.fields:
            if f.name in folded:
                continue
            if f.fmt == "record":
                names += [export_ground.slot_item_name(f.name, k, m.name) for k in range(MAX_STARS) for m in f.record]
            else:
                names.append(f.name.upper())
        if spec.is_command:
            got = [a.get("name") for a in commands[spec.name].findall("x:ArgumentList/x:Argument", XTCE_NS)]
            assert got == names, spec.name
        else:
            entries = containers[spec.name].find("x:EntryList", XTCE_NS)
            got = [e.get("parameterRef") for e in entries]
            assert got == [export_ground.xtce_parameter_name(spec.name, n) for n in names], spec.name
