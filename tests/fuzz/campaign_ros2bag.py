"""A seeded mutation campaign of ROS 2 bags (MCAP and sqlite3 storage, metadata.yaml) x slamreplay's commands.

    nice .venv/bin/python tests/fuzz/campaign_ros2bag.py --mutants 300 --seed 7 --out /tmp/ros2bag-campaign.json
    .venv/bin/python tests/fuzz/campaign_ros2bag.py --report /tmp/ros2bag-campaign.json   # the table again

Each mutant is a bag folder (metadata.yaml + one storage file) built from a base by one operator drawn from
``numpy.random.default_rng([seed, index, kind])``, and goes through `inspect DIR`, `inspect FILE`, `run DIR`,
`recover FILE`, `record ros2 DIR` and `evaluate DIR --topic` in a worker process with an address-space limit
(its warm size + 1 GiB) and an alarm per command (tests/fuzz/runner.py's ``_call``). Kinds: ``mcap1`` (rosbags'
writer: one uncompressed, CRC-less chunk), ``mcapN`` (re-written by the mcap library: zstd chunks, CRCs),
``mcapfx`` (mcap_ros2's writer, a hand-written metadata.yaml), ``db3`` (sqlite3), ``yaml-mcap`` and ``yaml-db3``
(metadata.yaml damaged: numbers, aliases, nesting, paths to a FIFO or a folder, storage, compression...).
Outcomes: ok (exit 0), clean (exit 1, or 2 with one line), internal, multiline, memory (a MemoryError
anywhere: an allocation sized by the file), hang, died, stderr (exit 0 or 1 with something on stderr).
Issue 37, item 8: 1,800 mutants before and after the check of recorder/importers/ros2bag_check.py.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import multiprocessing.connection as mpc
import os
import re
import resource
import shutil
import signal
import struct
import sys
import time
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))
WORK = Path(os.environ.get("ROS2BAG_CAMPAIGN_DIR", "/tmp/slamreplay-ros2bag-campaign"))

KINDS = ("mcap1", "mcapN", "mcapfx", "db3", "yaml-mcap", "yaml-db3")
HUGE = ((1 << 63) - 1, (1 << 64) - 1, 1 << 63, 0xFFFF_FFFF_FFFF_FFF0, 1 << 62, 1 << 40, 1 << 32, 0xFFFF_FFFF,
        0x7FFF_FFFF, 1 << 31)


def make_bases(folder: Path) -> dict[str, Path]:
    """Bag folders, one per kind of storage."""
    from slamreplay.recorder.sim.ros2bag import write_bag
    from tests.fuzz.mutate import _rewrite

    folder.mkdir(parents=True, exist_ok=True)
    out = {}
    for name, storage in (("mcap1", "mcap"), ("db3", "sqlite3")):
        p = folder / name
        if not p.exists():
            write_bag(p, storage, seconds=1.0)
        out[name] = p
    p = folder / "mcapN"
    if not p.exists():
        shutil.copytree(out["mcap1"], p)
        f = next(p.glob("*.mcap"))
        f.write_bytes(_rewrite(f.read_bytes()))  # mcap's writer, 16 KB chunks: several chunks and indexes
    out["mcapN"] = p
    p = folder / "mcapfx"
    if not p.exists():
        sys.path.insert(0, str(REPO / "tests" / "replay"))
        from ros2_fixtures import write_ros2_bag

        write_ros2_bag(p, n=30)
    out["mcapfx"] = p
    out["yaml-mcap"], out["yaml-db3"] = out["mcap1"], out["db3"]
    rec = folder / "rec.mcap"
    if not rec.exists():
        from slamreplay.recorder.importers.ros2bag import import_ros2_bag

        import_ros2_bag(out["mcap1"], rec, ground_truth_frame="map")
    return out


def storage_file(bag: Path) -> Path:
    return next(f for f in sorted(bag.iterdir()) if f.suffix in (".mcap", ".db3"))


# ------------------------------------------------------------------------------------------------ MCAP


def _records(data: bytes) -> list[tuple[int, int, int]]:
    from tests.fuzz.mutate import top_level_records

    return top_level_records(data)


def mutate_mcap(data: bytes, rng: np.random.Generator, seed: int, index: int) -> tuple[bytes, dict[str, Any]]:
    from tests.fuzz.mutate import OPS, OUTSIDER_OPS, mutant

    ops = (*OPS, *OUTSIDER_OPS, "dup_record", "len_max", "index_field", "index_field", "chunk_field",
           "message_len", "stats_field")
    op = ops[int(rng.integers(0, len(ops)))]
    recs = _records(data)
    buf = bytearray(data)
    if op in OPS or op in OUTSIDER_OPS:
        m = mutant(data, seed, index, op)
        return m.data, m.recipe
    if op == "dup_record":
        at, opcode, total = recs[int(rng.integers(0, len(recs)))]
        buf[at + total:at + total] = buf[at:at + total]
        return bytes(buf), {"op": op, "record_at": at, "opcode": opcode}
    if op == "len_max":
        at, opcode, _ = recs[int(rng.integers(0, len(recs)))]
        value = int(HUGE[int(rng.integers(0, 4))])
        struct.pack_into("<Q", buf, at + 1, value)
        return bytes(buf), {"op": op, "record_at": at, "opcode": opcode, "value": value}
    if op in ("index_field", "chunk_field", "stats_field", "message_len"):
        want = {"index_field": (8, 7, 13, 10, 12), "chunk_field": (6,), "stats_field": (11, 14, 3, 4),
                "message_len": (5, 6)}[op]
        cands = [r for r in recs if r[1] in want] or recs
        at, opcode, total = cands[int(rng.integers(0, len(cands)))]
        width = 8 if rng.random() < 0.6 else 4
        if total - 9 < width:
            return bytes(buf), {"op": op, "noop": True}
        field = at + 9 + (8 * int(rng.integers(0, max(1, (total - 9 - width) // 8 + 1))) if width == 8
                          else int(rng.integers(0, total - 9 - width + 1)))
        field = min(field, at + total - width)
        value = int(HUGE[int(rng.integers(0, len(HUGE)))]) if rng.random() < 0.7 else int(rng.integers(0, 1 << 20))
        value &= (1 << (8 * width)) - 1
        struct.pack_into("<Q" if width == 8 else "<I", buf, field, value)
        return bytes(buf), {"op": op, "record_at": at, "opcode": opcode, "field_at": field, "value": value,
                            "width": width}
    raise ValueError(op)


# ------------------------------------------------------------------------------------------------ sqlite


def mutate_db3(data: bytes, rng: np.random.Generator) -> tuple[bytes, dict[str, Any]]:
    ops = ("bitflip", "zero_run", "truncate", "page_zero", "page_dup", "header_field", "overwrite8",
           "huge_length", "random_body", "page_swap")
    op = ops[int(rng.integers(0, len(ops)))]
    buf, n = bytearray(data), len(data)
    page = 4096
    pages = n // page
    if op == "bitflip":
        flips = []
        for _ in range(int(rng.integers(1, 9))):
            at, bit = int(rng.integers(0, n)), int(rng.integers(0, 8))
            buf[at] ^= 1 << bit
            flips.append([at, bit])
        return bytes(buf), {"op": op, "flips": flips}
    if op == "zero_run":
        at, length = int(rng.integers(0, n)), int(rng.integers(1, 513))
        buf[at:at + length] = bytes(len(buf[at:at + length]))
        return bytes(buf), {"op": op, "at": at, "length": length}
    if op == "truncate":
        at = int(rng.integers(0, n))
        return bytes(buf[:at]), {"op": op, "at": at}
    if op == "page_zero":
        p = int(rng.integers(0, pages))
        buf[p * page:(p + 1) * page] = bytes(page)
        return bytes(buf), {"op": op, "page": p}
    if op in ("page_dup", "page_swap"):
        a, b = (int(x) for x in rng.integers(0, pages, 2))
        pa, pb = bytes(buf[a * page:(a + 1) * page]), bytes(buf[b * page:(b + 1) * page])
        buf[b * page:(b + 1) * page] = pa
        if op == "page_swap":
            buf[a * page:(a + 1) * page] = pb
        return bytes(buf), {"op": op, "from": a, "to": b}
    if op == "header_field":  # the 100-byte database header, and page headers' cell counts/offsets
        fields = ((16, 2), (18, 1), (19, 1), (20, 1), (24, 4), (28, 4), (32, 4), (36, 4), (40, 4), (44, 4),
                  (48, 4), (52, 4), (56, 4), (64, 4), (92, 4), (96, 4))
        if rng.random() < 0.5:
            at, width = fields[int(rng.integers(0, len(fields)))]
        else:  # a b-tree page header: cell count (3), cell content start (5), right pointer (8)
            p = int(rng.integers(1, pages))
            off, width = ((3, 2), (5, 2), (8, 4), (1, 2))[int(rng.integers(0, 4))]
            at = p * page + off
        value = int(rng.choice([0, 1, 0xFF, 0xFFFF, 0x7FFF_FFFF, 0xFFFF_FFFF, int(rng.integers(0, 1 << 16))]))
        value &= (1 << (8 * width)) - 1
        buf[at:at + width] = value.to_bytes(width, "big")
        return bytes(buf), {"op": op, "at": at, "width": width, "value": value}
    if op == "overwrite8":
        at = int(rng.integers(0, n - 8))
        buf[at:at + 8] = rng.integers(0, 256, 8, dtype=np.uint8).tobytes()
        return bytes(buf), {"op": op, "at": at}
    if op == "huge_length":
        at = int(rng.integers(0, n - 8))
        value = int(HUGE[int(rng.integers(0, len(HUGE)))])
        buf[at:at + 8] = (value & ((1 << 64) - 1)).to_bytes(8, "big")
        return bytes(buf), {"op": op, "at": at, "value": value}
    if op == "random_body":
        size = int(rng.integers(0, 8193))
        body = rng.integers(0, 256, size, dtype=np.uint8).tobytes()
        if rng.random() < 0.5:
            body = data[:100] + body
        return body, {"op": op, "size": size}
    raise ValueError(op)


# ------------------------------------------------------------------------------------------------ yaml

NUMBERS = ("-1", "-9223372036854775808", "9223372036854775807", "18446744073709551616", "1e400", "-1e400",
           ".nan", "0x7fffffffffffffff", "''", "null", "[]", "{}", "1.5", "99999999999999999999999999999999")


def mutate_yaml(text: str, storage: str, rng: np.random.Generator) -> tuple[bytes, dict[str, Any], dict[str, bytes]]:
    """(new metadata.yaml, recipe, extra files to write beside it)."""
    ops = ("bitflip", "truncate", "number", "number", "line_dup", "line_del", "alias_bomb", "paths", "storage_id",
           "compression", "version", "msgtype", "serialization", "nest", "key_rename", "not_utf8", "indent")
    op = ops[int(rng.integers(0, len(ops)))]
    lines = text.splitlines(keepends=True)
    extra: dict[str, bytes] = {}
    raw = text.encode()
    if op == "bitflip":
        buf = bytearray(raw)
        flips = []
        for _ in range(int(rng.integers(1, 5))):
            at, bit = int(rng.integers(0, len(buf))), int(rng.integers(0, 8))
            buf[at] ^= 1 << bit
            flips.append([at, bit])
        return bytes(buf), {"op": op, "flips": flips}, extra
    if op == "truncate":
        at = int(rng.integers(0, len(raw)))
        return raw[:at], {"op": op, "at": at}, extra
    if op == "not_utf8":
        at = int(rng.integers(0, len(raw)))
        return raw[:at] + b"\xff\xfe" + raw[at:], {"op": op, "at": at}, extra
    if op == "number":
        spots = [m for m in re.finditer(r"(?<=: )\d+|(?<=- )\d+", text)]
        m = spots[int(rng.integers(0, len(spots)))]
        value = NUMBERS[int(rng.integers(0, len(NUMBERS)))]
        return (text[:m.start()] + value + text[m.end():]).encode(), {"op": op, "at": m.start(), "value": value}, extra
    if op in ("line_dup", "line_del", "indent"):
        i = int(rng.integers(0, len(lines)))
        if op == "line_dup":
            lines.insert(i, lines[i])
        elif op == "line_del":
            del lines[i]
        else:
            lines[i] = "  " + lines[i]
        return "".join(lines).encode(), {"op": op, "line": i}, extra
    if op == "alias_bomb":  # billion laughs as a value the reader walks (topics) or ignores (custom_data)
        bomb = "".join(f"  a{k}: &a{k} [" + ", ".join([f"*a{k - 1}"] * 9) + "]\n" for k in range(1, 9))
        where = "custom_data" if rng.random() < 0.5 else "topics_with_message_count"
        new = re.sub(rf"  {where}:.*?(?=\n  \w)", f"  {where}: *a8", text, count=1, flags=re.S)
        return ("rosbag2_bagfile_information:\n  a0: &a0 [x]\n" + bomb + new.split("\n", 1)[1]).encode(), \
            {"op": op, "where": where}, extra
    if op == "paths":
        choice = int(rng.integers(0, 6))
        name = ["metadata.yaml", "../../../../etc/passwd", "/dev/zero", "fifo.mcap", "big.mcap", "dir.mcap"][choice]
        if name == "fifo.mcap":
            extra["fifo"] = b"fifo.mcap"
        if name == "dir.mcap":
            extra["dir"] = b"dir.mcap"
        if name == "big.mcap":
            extra["big"] = b"big.mcap"
        new = re.sub(r"relative_file_paths:\n  - \S+", f"relative_file_paths:\n  - {name}", text)
        return new.encode(), {"op": op, "path": name}, extra
    if op == "storage_id":
        other = {"mcap": "sqlite3", "sqlite3": "mcap"}[storage]
        value = [other, "", "x" * 300, "memory"][int(rng.integers(0, 4))]
        return re.sub(r"storage_identifier: \S+", f"storage_identifier: {value}", text).encode(), \
            {"op": op, "value": value}, extra
    if op == "compression":
        mode = ["file", "message", "FILE", "none"][int(rng.integers(0, 4))]
        fmt = ["zstd", "lz4", ""][int(rng.integers(0, 3))]
        new = text.replace("compression_format: ''", f"compression_format: {fmt}").replace(
            "compression_mode: ''", f"compression_mode: {mode}")
        return new.encode(), {"op": op, "mode": mode, "format": fmt}, extra
    if op == "version":
        value = ["10", "-1", "0", "1", "4", "99999999999999999999", "'9'", "null"][int(rng.integers(0, 8))]
        new = re.sub(r"version: \d+", f"version: {value}", text) if "version:" in text else \
            text.replace("rosbag2_bagfile_information:\n", f"rosbag2_bagfile_information:\n  version: {value}\n")
        return new.encode(), {"op": op, "value": value}, extra
    if op == "msgtype":
        types = re.findall(r"type: (\S+)", text)
        old = types[int(rng.integers(0, len(types)))]
        value = ["x", "a/b", "nav_msgs/msg/Odometry", "sensor_msgs/msg/Image", "a/msg/" + "b" * 500,
                 "tf2_msgs/msg/TFMessage"][int(rng.integers(0, 6))]
        return text.replace(f"type: {old}", f"type: {value}", 1).encode(), {"op": op, "old": old, "value": value}, extra
    if op == "serialization":
        return text.replace("serialization_format: cdr", "serialization_format: ros1", 1).encode(), {"op": op}, extra
    if op == "nest":
        depth = int(rng.choice([100, 1000, 100000]))
        return text.replace("custom_data: null", "custom_data: " + "[" * depth + "]" * depth).encode(), \
            {"op": op, "depth": depth}, extra
    if op == "key_rename":
        keys = re.findall(r"(\w+):", text)
        k = keys[int(rng.integers(0, len(keys)))]
        return text.replace(f"{k}:", f"{k}x:", 1).encode(), {"op": op, "key": k}, extra
    raise ValueError(op)


# ------------------------------------------------------------------------------------------------ running


def build(kind: str, bases: dict[str, str], seed: int, index: int, dest: Path) -> dict[str, Any]:
    """The mutant bag folder ``dest``; its recipe."""
    rng = np.random.default_rng([seed, index, KINDS.index(kind)])
    base = Path(bases[kind])
    shutil.rmtree(dest, ignore_errors=True)
    shutil.copytree(base, dest)
    store = storage_file(dest)
    if kind.startswith("mcap"):
        data, recipe = mutate_mcap(store.read_bytes(), rng, seed, index * 10 + KINDS.index(kind))
        store.write_bytes(data)
    elif kind == "db3":
        data, recipe = mutate_db3(store.read_bytes(), rng)
        store.write_bytes(data)
    else:
        storage = "mcap" if kind == "yaml-mcap" else "sqlite3"
        text, recipe, extra = mutate_yaml((dest / "metadata.yaml").read_text(), storage, rng)
        (dest / "metadata.yaml").write_bytes(text)
        if "fifo" in extra:
            os.mkfifo(dest / "fifo.mcap")
        if "dir" in extra:
            (dest / "dir.mcap").mkdir()
        if "big" in extra:
            with open(dest / "big.mcap", "wb") as f:
                f.truncate(1 << 34)  # a sparse 16 GiB file
    return recipe


def commands(kind: str, bag: Path, out: Path) -> dict[str, list[str]]:
    store = storage_file(bag)
    cmds = {"inspect-dir": ["inspect", str(bag)],
            "run-dir": ["run", str(bag), "--pipeline", "odometry", "--out", str(out / "run"), "--quiet"],
            "record-ros2": ["record", "ros2", str(bag), "--out", str(out / "rec.mcap"), "--quiet"],
            "evaluate-dir": ["evaluate", str(bag), "--topic", "/wheel/odom" if kind == "mcapfx" else "/odom",
                             "--recording", str(WORK / "bases" / "rec.mcap"), "--out", str(out / "ev"), "--quiet"]}
    if not kind.startswith("yaml"):
        cmds["inspect-file"] = ["inspect", str(store)]
        cmds["recover-file"] = ["recover", str(store), "--out", str(out / "fixed.mcap")]
    return cmds


def classify(outcome: str, rc: int | None, stdout: str, stderr: str) -> tuple[str, str]:
    lines = [ln for ln in stderr.strip().splitlines() if ln.strip()]
    text = stdout + stderr
    if outcome == "hang":
        return "hang", ""
    if outcome == "internal":
        return "internal", (lines[-1] if lines else "")[:300]
    if "MemoryError" in text or "Cannot allocate memory" in text:
        return "memory", (lines[0] if lines else "")[:300]
    if rc == 2:
        if len(lines) != 1 or "Traceback" in stderr:
            return "multiline", stderr[:300]
        return "clean", lines[0][:300]
    if rc in (0, 1) and stderr.strip():
        return "stderr", stderr.strip()[:300]
    if rc == 1:
        return "clean", next((ln.strip() for ln in stdout.splitlines() if "problem" in ln or "cannot" in ln), "")[:300]
    return "ok", next((ln.strip() for ln in stdout.splitlines() if "cannot import" in ln), "")[:300]


def worker(conn: mpc.Connection, bases: dict[str, str], work: str, headroom: int, limit_s: int) -> None:
    from tests.fuzz.runner import _call, _on_alarm

    signal.signal(signal.SIGALRM, _on_alarm)
    root = Path(work)
    root.mkdir(parents=True, exist_ok=True)
    for kind in ("mcap1", "db3"):  # warm
        out = root / "warm"
        shutil.rmtree(out, ignore_errors=True)
        out.mkdir()
        for argv in commands(kind, Path(bases[kind]), out).values():
            _call(argv, 60)
    with open("/proc/self/status") as f:
        peak = next(int(line.split()[1]) * 1024 for line in f if line.startswith("VmPeak"))
    resource.setrlimit(resource.RLIMIT_AS, (peak + headroom, peak + headroom))
    conn.send("ready")
    done = 0
    while done < 60:
        task = conn.recv()
        if task is None:
            return
        kind, seed, index = task
        bag = root / "bag"
        out = root / "out"
        shutil.rmtree(out, ignore_errors=True)
        out.mkdir()
        recipe = build(kind, bases, seed, index, bag)
        results = {}
        for name, argv in commands(kind, bag, out).items():
            t0 = time.perf_counter()
            outcome, rc, stdout, stderr = _call(argv, limit_s)
            what, line = classify(outcome, rc, stdout, stderr)
            results[name] = {"outcome": what, "exit": rc, "line": line, "s": round(time.perf_counter() - t0, 3)}
            if what not in ("ok", "clean"):
                results[name]["tail"] = (stderr + stdout)[-1500:]
            for p in list(out.iterdir()):
                shutil.rmtree(p, ignore_errors=True) if p.is_dir() else p.unlink()
        done += 1
        conn.send({"kind": kind, "seed": seed, "index": index, "recipe": recipe, "results": results})


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--mutants", type=int, default=300, help="per kind")
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--kinds", default=",".join(KINDS))
    ap.add_argument("--out", default=str(WORK / "results.json"))
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--limit-s", type=int, default=20)
    args = ap.parse_args()
    bases = {k: str(v) for k, v in make_bases(WORK / "bases").items()}
    kinds = args.kinds.split(",")
    pending = [(k, args.seed, i) for i in range(args.mutants) for k in kinds][::-1]
    ctx = mp.get_context("spawn")
    results: list[dict[str, Any]] = []

    def spawn(n: int) -> dict[str, Any]:
        a, b = ctx.Pipe()
        p = ctx.Process(target=worker, args=(b, bases, str(WORK / "work" / f"w{n}"), 1 << 30, args.limit_s),
                        daemon=True)
        p.start()
        b.close()
        assert a.poll(300) and a.recv() == "ready"
        return {"n": n, "p": p, "c": a, "task": None, "since": 0.0, "done": 0}

    slots = [spawn(n) for n in range(args.workers)]
    t_start = time.time()
    while pending or any(s["task"] for s in slots):
        for s in slots:
            if s["task"] is None and pending:
                s["task"] = pending.pop()
                s["since"] = time.monotonic()
                s["c"].send(s["task"])
        busy = [s for s in slots if s["task"]]
        ready = mpc.wait([s["c"] for s in busy], timeout=1.0)
        for s in busy:
            if s["c"] in ready:
                try:
                    results.append(s["c"].recv())
                    s["done"] += 1
                    s["task"] = None
                    if s["done"] >= 60:
                        s["p"].join(30)
                        slots[slots.index(s)] = spawn(s["n"])
                    continue
                except EOFError:
                    why = f"worker died ({s['p'].exitcode})"
                    what = "died"
            elif time.monotonic() - s["since"] > 6 * args.limit_s + 30:
                why, what = "worker stopped answering", "hang"
            else:
                continue
            kind, seed, index = s["task"]
            results.append({"kind": kind, "seed": seed, "index": index, "recipe": {},
                            "results": {"all": {"outcome": what, "exit": None, "line": why}}})
            s["p"].kill()
            s["p"].join()
            slots[slots.index(s)] = spawn(s["n"])
        if len(results) % 50 == 0 and results:
            print(f"{len(results)} done, {time.time() - t_start:.0f} s", file=sys.stderr, flush=True)
    for s in slots:
        s["c"].send(None)
        s["p"].join(10)
    Path(args.out).write_text(json.dumps(results, indent=0, default=str))
    report(results)


def report(results: list[dict[str, Any]]) -> None:
    table: dict[tuple[str, str], Counter[str]] = {}
    for r in results:
        for cmd, e in r["results"].items():
            table.setdefault((r["kind"], cmd), Counter())[e["outcome"]] += 1
    outs = ("ok", "clean", "internal", "multiline", "memory", "hang", "died", "stderr")
    print(f"| kind | command | n | {' | '.join(outs)} |")
    tot: dict[str, Counter[str]] = {}
    for (k, c), cnt in sorted(table.items()):
        print(f"| {k} | {c} | {sum(cnt.values())} | " + " | ".join(str(cnt[o]) for o in outs) + " |")
        tot.setdefault(c, Counter()).update(cnt)
    for c, cnt in sorted(tot.items()):
        print(f"| all | {c} | {sum(cnt.values())} | " + " | ".join(str(cnt[o]) for o in outs) + " |")
    bad = [(r["kind"], r["index"], cmd, e) for r in results for cmd, e in r["results"].items()
           if e["outcome"] not in ("ok", "clean")]
    print(f"\n{len(bad)} unclean command outcomes in {len({(k, i) for k, i, _, _ in bad})} mutants")
    by: Counter[str] = Counter()
    for *_, e in bad:
        key = re.sub(r"\d+", "N", e["line"])[:140]
        by[f"{e['outcome']}: {key}"] += 1
    for k, n in by.most_common(40):
        print(f"{n:5d}  {k}")


if __name__ == "__main__":
    if sys.argv[1:2] == ["--report"]:
        report(json.loads(Path(sys.argv[2]).read_text()))
    else:
        main()
