#!/usr/bin/env python3
"""Beckhoff's AdsLib, through PyPI pyads, as an ADS client the tests can drive.

It connects with AdsLib's own in-process router (no TwinCAT needed: a local AMS
address and a route to HOST:PORT), then takes one command a line on stdin and answers
one Erlang term a line on stdout. Device notifications arrive on AdsLib's thread and
are printed as they come: {notification, Handle, FileTime, Value}.

    info | state | write_control ADS DEV
    read NAME TYPE | write NAME TYPE VALUE
    handle NAME | read_handle H TYPE | write_handle H TYPE VALUE | release H
    info_by_name NAME
    sum_read NAME ... | sum_write NAME TYPE VALUE [NAME TYPE VALUE ...]
    notify NAME TYPE on_change|cyclic CYCLE_MS | del_notify NH UH
    bench_handle SECONDS NAME TYPE      (reads by one handle, as fast as it goes)
    bench_sum SECONDS NAME ...          (sum reads of the group, symbol info cached)
    bench_single SECONDS TYPE NAME ...  (the group read one handle at a time)
    quit

TYPE is a PLC type name: BOOL, BYTE, SINT, INT, UINT, WORD, DINT, UDINT, DWORD, LINT,
ULINT, REAL, LREAL, STRING, TIME, DATE. VALUE is a Python literal.
"""

import argparse
import ctypes
import ast
import math
import sys
import threading
import time

import pyads

TYPES = {
    "BOOL": pyads.PLCTYPE_BOOL, "BYTE": pyads.PLCTYPE_BYTE, "USINT": pyads.PLCTYPE_USINT,
    "SINT": pyads.PLCTYPE_SINT, "INT": pyads.PLCTYPE_INT, "UINT": pyads.PLCTYPE_UINT,
    "WORD": pyads.PLCTYPE_WORD, "DINT": pyads.PLCTYPE_DINT, "UDINT": pyads.PLCTYPE_UDINT,
    "DWORD": pyads.PLCTYPE_DWORD, "LINT": pyads.PLCTYPE_LINT, "ULINT": pyads.PLCTYPE_ULINT,
    "REAL": pyads.PLCTYPE_REAL, "LREAL": pyads.PLCTYPE_LREAL, "STRING": pyads.PLCTYPE_STRING,
    "TIME": pyads.PLCTYPE_TIME, "DATE": pyads.PLCTYPE_DATE,
}

lock = threading.Lock()


def erl(term):
    if isinstance(term, bool):
        return "true" if term else "false"
    if isinstance(term, int):
        return str(term)
    if isinstance(term, float):
        if math.isnan(term):
            return "nan"
        if math.isinf(term):
            return "infinity" if term > 0 else "neg_infinity"
        text = repr(term)
        mantissa, _, exponent = text.partition("e")
        if "." not in mantissa:
            mantissa += ".0"
        return mantissa + ("e" + exponent if exponent else "")
    if isinstance(term, str):
        return erl(term.encode("latin-1"))
    if isinstance(term, (bytes, bytearray)):
        return "<<" + ",".join(str(b) for b in term) + ">>"
    if isinstance(term, list):
        return "[" + ",".join(erl(t) for t in term) + "]"
    if isinstance(term, tuple):
        return "{" + ",".join(erl(t) for t in term) + "}"
    if isinstance(term, Atom):
        return term.name
    raise TypeError(repr(term))


class Atom:
    def __init__(self, name):
        self.name = name


OK = Atom("ok")


def say(term):
    with lock:
        sys.stdout.write(erl(term) + "\n")
        sys.stdout.flush()


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--host", default="127.0.0.1")
    parser.add_argument("--port", type=int, required=True)
    parser.add_argument("--target", required=True)
    parser.add_argument("--target-port", type=int, default=851)
    parser.add_argument("--local", required=True)
    args = parser.parse_args()

    address = "%s:%d" % (args.host, args.port)
    pyads.open_port()
    pyads.set_local_address(args.local)
    pyads.add_route(args.target, address)
    plc = pyads.Connection(args.target, args.target_port, address)
    plc.open()
    local = plc.get_local_address()
    say((Atom("ready"), local.port))

    for line in sys.stdin:
        words = line.split()
        if not words:
            continue
        if words[0] == "quit":
            break
        try:
            say(command(plc, words[0], words[1:]))
        except pyads.ADSError as e:
            say((Atom("error"), e.err_code))
        except Exception as e:  # the test wants every failure as an answer, not a hang
            say((Atom("error"), "%s: %s" % (type(e).__name__, e)))
    plc.close()


def command(plc, cmd, args):
    if cmd == "info":
        name, version = plc.read_device_info()
        return (OK, name, (version.version, version.revision, version.build))
    if cmd == "state":
        ads_state, device_state = plc.read_state()
        return (OK, ads_state, device_state)
    if cmd == "write_control":
        plc.write_control(int(args[0]), int(args[1]), 0, pyads.PLCTYPE_INT)
        return OK
    if cmd == "read":
        return (OK, plc.read_by_name(args[0], TYPES[args[1]]))
    if cmd == "write":
        plc.write_by_name(args[0], ast.literal_eval(args[2]), TYPES[args[1]])
        return OK
    if cmd == "handle":
        return (OK, plc.get_handle(args[0]))
    if cmd == "read_handle":
        return (OK, plc.read_by_name("", TYPES[args[1]], handle=int(args[0])))
    if cmd == "write_handle":
        plc.write_by_name("", ast.literal_eval(args[2]), TYPES[args[1]], handle=int(args[0]))
        return OK
    if cmd == "release":
        plc.release_handle(int(args[0]))
        return OK
    if cmd == "info_by_name":
        info = pyads.pyads_ex.adsGetSymbolInfo(plc._port, plc._adr, args[0])
        return (OK, info.name, info.symbol_type, info.iGroup, info.iOffs, info.size,
                info.dataType)
    if cmd == "sum_read":
        values = plc.read_list_by_name(args)
        return (OK, [values[n] for n in args])
    if cmd == "sum_write":
        triples = [args[i: i + 3] for i in range(0, len(args), 3)]
        values = {n: ast.literal_eval(v) for n, _t, v in triples}
        result = plc.write_list_by_name(values)
        return (OK, [result[n] for n, _t, _v in triples])
    if cmd == "notify":
        name, ptype, mode, cycle_ms = args[0], TYPES[args[1]], args[2], float(args[3])
        trans = pyads.ADSTRANS_SERVERONCHA if mode == "on_change" else pyads.ADSTRANS_SERVERCYCLE

        @plc.notification(ptype, timestamp_as_filetime=True)
        def callback(handle, _name, timestamp, value):
            say((Atom("notification"), handle, timestamp, value))

        attr = pyads.NotificationAttrib(ctypes.sizeof(ptype), trans, 0, cycle_ms)
        nh, uh = plc.add_device_notification(name, attr, callback)
        return (OK, nh, uh)
    if cmd == "del_notify":
        plc.del_device_notification(int(args[0]), int(args[1]))
        return OK
    if cmd == "bench_handle":
        seconds, name, ptype = float(args[0]), args[1], TYPES[args[2]]
        handle = plc.get_handle(name)
        count, start = 0, time.perf_counter()
        while time.perf_counter() - start < seconds:
            plc.read_by_name("", ptype, handle=handle)
            count += 1
        elapsed = time.perf_counter() - start
        plc.release_handle(handle)
        return (OK, count, int(elapsed * 1e6))
    if cmd == "bench_sum":
        seconds, names = float(args[0]), args[1:]
        plc.read_list_by_name(names)  # symbol info fetched once and cached
        count, start = 0, time.perf_counter()
        while time.perf_counter() - start < seconds:
            plc.read_list_by_name(names)
            count += 1
        return (OK, count, int((time.perf_counter() - start) * 1e6))
    if cmd == "bench_single":
        seconds, ptype, names = float(args[0]), TYPES[args[1]], args[2:]
        handles = [plc.get_handle(n) for n in names]
        count, start = 0, time.perf_counter()
        while time.perf_counter() - start < seconds:
            for h in handles:
                plc.read_by_name("", ptype, handle=h)
            count += 1
        elapsed = time.perf_counter() - start
        for h in handles:
            plc.release_handle(h)
        return (OK, count, int(elapsed * 1e6))
    return (Atom("error"), "unknown command " + cmd)


if __name__ == "__main__":
    main()
