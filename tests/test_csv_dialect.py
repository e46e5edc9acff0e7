"""Spreadsheets as Europe saves them (issue 26, part 6): ';' between fields, decimal commas, a UTF-8 BOM,
CR LF, a trailing ';', quoted "1,5" — read, with a note saying how, bit-identical to the same data
written with ',' and '.'; a file that cannot be told apart refused, naming the line, the field and what
to re-save it as."""

import csv
import io
import json

import numpy as np
import pytest
from conftest import PAPER

from eyetohand.cli import main
from eyetohand.core import InputError, load_image_points, load_pairs, pairs_from_text, read_csv

TRAIN = PAPER / "calibration_points.csv"
CHECK = PAPER / "check_points.csv"


def excel(text: str, *, sep=";", bom=True, crlf=True, trailing=False, quote_all=False) -> bytes:
    """``text`` (',' and '.') as a spreadsheet in a decimal-comma locale saves it."""
    out = io.StringIO()
    w = csv.writer(
        out,
        delimiter=sep,
        lineterminator="\r\n" if crlf else "\n",
        quoting=csv.QUOTE_ALL if quote_all else csv.QUOTE_MINIMAL,
    )
    for k, row in enumerate(csv.reader(text.splitlines())):
        cells = row if k == 0 else [c.replace(".", ",") for c in row]
        w.writerow(cells + ([""] if trailing else []))
    return (("\ufeff" if bom else "") + out.getvalue()).encode("utf-8")


def run(capsys, *argv):
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


@pytest.mark.parametrize(
    "style",
    [
        {},  # German / French Excel: BOM, CR LF, ';', decimal commas
        {"trailing": True},
        {"quote_all": True},
        {"bom": False, "crlf": False},
        {"sep": "\t"},
    ],
    ids=["excel", "trailing-sep", "quoted", "plain", "tab"],
)
def test_paper_pairs_as_excel_saves_them_read_bit_identical(tmp_path, style):
    path = tmp_path / "pairs.csv"
    path.write_bytes(excel(TRAIN.read_text(), **style))
    given, read = load_pairs(TRAIN), load_pairs(path)
    assert read.sha256() == given.sha256()
    assert np.array_equal(read.uv_px, given.uv_px) and np.array_equal(read.xyz_mm, given.xyz_mm)
    assert read.ids == given.ids
    sep = "tab" if style.get("sep") == "\t" else "';'"
    germans = " (German/French Excel)" if sep == "';'" else ""
    assert read.notes == (f"{path}: read as {sep}-separated with decimal commas{germans}",)


def test_calibrate_on_german_excel_files_is_bit_identical(tmp_path, capsys):
    """The paper's pairs and check points written as German Excel writes them: ``calibrate`` gives the
    same calibration, bit for bit, and says how it read them."""
    de_train, de_check = tmp_path / "pairs.csv", tmp_path / "check.csv"
    de_train.write_bytes(excel(TRAIN.read_text()))
    de_check.write_bytes(excel(CHECK.read_text(), trailing=True))
    runs = []
    for train, check, name in ((TRAIN, CHECK, "given"), (de_train, de_check, "excel")):
        code, out, err = run(capsys, "calibrate", train, "--check", check, "-o", tmp_path / f"{name}.json")
        assert code == 0, err
        runs.append((out, err, json.loads((tmp_path / f"{name}.json").read_text())))
    (out_a, err_a, cal_a), (out_b, err_b, cal_b) = runs
    assert f"note: {de_train}: read as ';'-separated with decimal commas (German/French Excel)\n" in err_b
    assert f"note: {de_check}: read as ';'-separated with decimal commas (German/French Excel)\n" in err_b
    assert "read as" not in err_a
    assert out_b.replace(str(tmp_path / "excel.json"), "") == out_a.replace(str(tmp_path / "given.json"), "")
    assert set(cal_b) == set(cal_a)
    for key in set(cal_a) - {"created_utc", "notes", "content_sha256", "fit"}:
        assert cal_b[key] == cal_a[key], key  # the model, statistics, region, uncertainty, pairs
    assert {**cal_b["fit"], "seconds": 0} == {**cal_a["fit"], "seconds": 0}


def test_image_points_and_evaluate_read_excel_too(tmp_path, capsys):
    cal = tmp_path / "cal.json"
    assert run(capsys, "calibrate", TRAIN, "-o", cal)[0] == 0
    de_check = tmp_path / "check.csv"
    de_check.write_bytes(excel(CHECK.read_text()))
    given = run(capsys, "evaluate", cal, CHECK, "--json", "--allow-outside")  # 2 of 9 outside the region
    read = run(capsys, "evaluate", cal, de_check, "--json", "--allow-outside")
    assert given[0] == read[0] == 0
    a, b = json.loads(given[1]), json.loads(read[1])
    assert b.pop("warnings") == [w.replace(str(CHECK), str(de_check)) for w in a.pop("warnings")]
    assert a == b
    assert f"note: {de_check}: read as ';'-separated" in read[2]
    points = "id,u,v\n0,441.615,1362.01\n1,667.076,1204.35\n"
    de_points = tmp_path / "points.csv"
    de_points.write_bytes(excel(points))
    table = load_image_points(de_points)
    assert table.uv_px.tolist() == [[441.615, 1362.01], [667.076, 1204.35]]
    assert table.notes == (f"{de_points}: read as ';'-separated with decimal commas (German/French Excel)",)


def test_conveyor_sessions_share_the_rule():
    from eyetohand.cell import load_session  # noqa: F401  (the package's loader, over the same csv_rows)
    from eyetohand.cell.conveyor.records import session_from_text

    text = "kind,id,u,v,x,y,z,e\nsight,a,10.5,20.25,,,,1000\ntouch,a,,,1.5,2,3,90000\n"
    a = session_from_text(text, "s.csv")
    b = session_from_text(excel(text).decode("utf-8-sig"), "s.csv")
    assert a.to_csv_text() == b.to_csv_text()


def test_commas_matching_the_header_are_separators_not_decimals():
    """``u,v,x,y`` and rows ``1,5,2,5``: four fields as the header has four: not ambiguous."""
    p = pairs_from_text("u,v,x,y\n1,5,2,5\n3,5,4,6\n", "p.csv")
    assert p.uv_px.tolist() == [[1, 5], [3, 5]] and p.notes[-1].endswith("plane z = 0 mm")
    assert not any("read as" in n for n in p.notes)


def test_quoted_decimal_commas_in_a_comma_file_are_read_and_said():
    p = pairs_from_text('u,v,x,y\n"1,5",2,3,4\n"3,25",5,6,7\n', "p.csv")
    assert p.uv_px[:, 0].tolist() == [1.5, 3.25]
    assert "p.csv: read as ','-separated with decimal commas in quoted fields" in p.notes


REFUSED = [
    (
        "split",
        "u,v,x,y\n1,5,2,5,3,5,4,5\n",
        "p.csv line 2: 8 fields, the header has 4: numbers with decimal commas in a file whose fields are "
        "separated by commas cannot be told apart; re-save it with ',' between fields and '.' as the "
        "decimal point (or ';' and decimal commas)",
    ),
    (
        "mixed",
        "id;u;v;x;y\n1;10,5;20;30;40\n2;11.5;21;31;41\n",
        "p.csv line 3, field 'u': '11.5' has a decimal point, but line 2 (u) has '10,5', a decimal comma: "
        "one file, one decimal mark; re-save it with one",
    ),
    (
        "thousands",
        "u;v;x;y\n1,500;2;3;4\n2;3;4,250;5\n",
        "p.csv line 2, field 'u': '1,500': a decimal comma or a thousands separator? Every comma in this "
        "file has three digits after it; re-save it with '.' as the decimal point and no thousands "
        "separators",
    ),
    (
        "grouped",
        "u;v;x;y\n1.234,5;2;3;4\n",
        "p.csv line 2, field 'u': '1.234,5' is not a number: thousands separators are not read; re-save the "
        "numbers without them",
    ),
    (
        "two separators",
        "u;a,v;x,y\n1;2,3;4,5\n",
        "p.csv line 1: the header and every row split into columns on ',' and ';' alike: which separates "
        "the fields? Re-save the file with one separator",
    ),
    ("pipe", "u|v|x|y\n1|2|3|4\n", "p.csv line 1: columns separated by '|', expected ',', ';' or tab"),
]


@pytest.mark.parametrize("label,text,message", REFUSED, ids=[r[0] for r in REFUSED])
def test_what_cannot_be_told_apart_is_refused_with_what_to_do(label, text, message, tmp_path, capsys):
    with pytest.raises(InputError) as exc:
        pairs_from_text(text, "p.csv")
    assert str(exc.value) == message
    path = tmp_path / "p.csv"
    path.write_text(text, encoding="utf-8")
    code, out, err = run(capsys, "calibrate", path)
    assert (code, out) == (2, "") and err == f"error: {message.replace('p.csv', str(path), 1)}\n"


def test_the_http_upload_reads_and_refuses_with_the_same_words(tmp_path):
    from fastapi.testclient import TestClient

    from eyetohand.server.app import create_app

    client = TestClient(create_app(tmp_path / "data"))
    text = excel(TRAIN.read_text()).decode("utf-8")  # the page sends the text; a BOM is one character
    r = client.post("/api/pairs/parse", json={"text": text.lstrip("\ufeff"), "source": "pairs.csv"})
    assert r.status_code == 200, r.text
    d = r.json()
    assert d["notes"][0] == "pairs.csv: read as ';'-separated with decimal commas (German/French Excel)"
    assert d["pairs"] == load_pairs(TRAIN).to_records()
    r = client.post("/api/pairs/parse", json={"text": REFUSED[1][1], "source": "p.csv"})
    assert r.status_code == 422 and REFUSED[1][2] in json.dumps(r.json()), r.text


def test_the_default_dialect_costs_no_scan():
    t = read_csv("u,v,x,y\n1.5,2,3,4\n", "p.csv")
    assert (t.separator, t.decimal_comma, t.note) == (",", False, None)
