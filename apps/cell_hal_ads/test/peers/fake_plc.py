#!/usr/bin/env python3
"""A fake TwinCAT PLC for the ADS tests: an ADS server over AMS/TCP.

It serves what a TwinCAT 3 PLC runtime serves to an ADS client and what pyads'
test server lacks: symbols with handles (0xF003/0xF005/0xF006), symbol info by name
(0xF009), the symbol version (0xF008), the symbol table upload (0xF00C/0xF00B), sum
commands (0xF080/0xF081/0xF082) and device notifications sent over the wire, on
change and cyclic, with FILETIME stamps. It is written from the ADS specification
only, independently of the client under test, and the test suite proves it with
Beckhoff's AdsLib (through pyads) before trusting it.

The test drives it through stdin, one command a line, and reads one answer a line on
stdout, written as an Erlang term:

    add NAME TYPENAME ADST SIZE HEX [nested]  -> {ok, Group, Offset}
    set NAME HEX                              -> ok      (on-change notifications)
    burst FT NAME HEX ... [; FT NAME HEX ...] -> ok      (values changed at given
                                                          FILETIME stamps, sent as one
                                                          notification frame)
    get NAME                                  -> {ok, <<...>>}
    remove NAME | retype NAME TYPENAME ADST SIZE HEX | bump
                                              -> ok      (a program change: the symbol
                                                          version moves on, handles of
                                                          changed symbols die)
    restart        -> ok   (the PLC runtime restarted, its program loaded again:
                            every handle and every notification on a symbol dies,
                            values go back to their initial ones, the symbol
                            version moves on; the connections and the notification
                            on the symbol version stay, as the router serves them)
    limit N        -> ok   (sum commands of more sub-commands are refused)
    frames         -> {ok, [<<...>>, ...]}  (every frame received since `clear')
    stats          -> {ok, #{...}}
    hold N         -> ok   (answers wait until N requests are waiting, then all go)
    wait_clients N TIMEOUT_MS -> ok | {error, timeout}   (when N clients are connected)
    wait_stat KEY N TIMEOUT_MS -> ok | {error, timeout}  (when stats KEY reaches N)
    stall | unstall -> ok  (the connections open now stop reading what clients send,
                            with a small receive buffer, until `unstall': a PLC
                            that hangs while its network stack lives on)
    report on|off  -> ok   (every value a client writes to a symbol, by handle, by
                            address or in a sum write, is then told as an event line
                            {notification, written, <<Name>>, <<the symbol's bytes>>}
                            before the write is answered)
    clear | mute | unmute | record on|off | drop | garbage HEX | quit

An NC with axes answers on AMS port 500 (see Nc below):

    nc_axis ID [MIN MAX [HOME_MS]] -> ok     (an axis, with software limits)
    nc_fail ID CODE  -> ok   (the axis's next move faults halfway with NC error CODE)
    nc_fault ID CODE -> ok   (the axis faults now)
    nc_pos ID POS    -> ok   (the axis's actual position is POS now: one at rest
                              pushed by hand)
    nc_get ID        -> {ok, #{...}}  (the axis as the NC has it)
    nc_channel ID AXIS_X AXIS_Y [AXIS_Z] -> ok   (an NC I interpolation channel
                              over those axes, its interpreter running DIN 66025
                              programs the system service's files hold)
    nc_channel_fail ID CODE -> ok   (the channel's next program faults halfway: its
                              axes stop there, the channel's error is CODE)
    nc_channel_get ID -> {ok, #{...}}  (the channel: its interpreter's state, error,
                              the program loaded, how many it ran, its path
                              override)
    file_get NAME    -> {ok, <<...>>} | {error, no_file}   (a file the system
                              service (AMS port 10000) holds)

Names with spaces are written with %20 for each space.
`nested` marks a structure field: found by name like TwinCAT finds them, not listed
in the uploaded table (which holds top-level symbols only).
"""

import argparse
import asyncio
import math
import os
import socket
import struct
import sys
import threading
import time
from urllib.parse import unquote

FILETIME_UNIX_EPOCH = 116444736000000000

IG_HNDBYNAME = 0xF003
IG_VALBYHND = 0xF005
IG_RELEASEHND = 0xF006
IG_VERSION = 0xF008
IG_INFOBYNAMEEX = 0xF009
IG_UPLOAD = 0xF00B
IG_UPLOADINFO = 0xF00C
IG_UPLOADINFO2 = 0xF00F
IG_SUM_READ = 0xF080
IG_SUM_WRITE = 0xF081
IG_SUM_READWRITE = 0xF082
IG_PLC_DATA = 0x4040

ERR_SERVICE = 0x701
ERR_GROUP = 0x702
ERR_OFFSET = 0x703
ERR_SIZE = 0x705
ERR_SYMBOL = 0x710
ERR_TRANSMODE = 0x713
ERR_NOTE_HANDLE = 0x714

AMS_HEADER = struct.Struct("<6sH6sHHHIII")
TCP_HEADER = struct.Struct("<HI")

MODE_CYCLIC = 3
MODE_ON_CHANGE = 4

# The target of a notification on the symbol version.
VERSION = "symbol version"


def filetime_now():
    return FILETIME_UNIX_EPOCH + time.time_ns() // 100


def erl(term):
    """An Erlang term's text for ints, floats, atoms (str), binaries (bytes), lists, tuples,
    maps."""
    if isinstance(term, bool):
        return "true" if term else "false"
    if isinstance(term, int):
        return str(term)
    if isinstance(term, float):
        return "%.17e" % term
    if isinstance(term, str):
        return term
    if isinstance(term, (bytes, bytearray)):
        return "<<" + ",".join(str(b) for b in term) + ">>"
    if isinstance(term, list):
        return "[" + ",".join(erl(t) for t in term) + "]"
    if isinstance(term, tuple):
        return "{" + ",".join(erl(t) for t in term) + "}"
    if isinstance(term, dict):
        return "#{" + ",".join(erl(k) + " => " + erl(v) for k, v in term.items()) + "}"
    raise TypeError(term)


class Symbol:
    def __init__(self, name, type_name, ads_type, size, value, group, offset, nested):
        self.name = name
        self.type_name = type_name
        self.ads_type = ads_type
        self.size = size
        self.value = bytearray(value.ljust(max(size, 1), b"\0")[: max(size, 1)])
        self.initial = bytes(self.value)
        self.group = group
        self.offset = offset
        self.nested = nested

    def entry(self):
        """The symbol entry: header, then name, type and comment each NUL-terminated."""
        name = self.name.encode("latin-1")
        tname = self.type_name.encode("latin-1")
        comment = b"fake"
        strings = name + b"\0" + tname + b"\0" + comment + b"\0"
        length = 30 + len(strings)
        return struct.pack("<IIIIIIHHH", length, self.group, self.offset, self.size,
                           self.ads_type, 0, len(name), len(tname), len(comment)) + strings


class Note:
    def __init__(self, conn, target, length, mode, cycle, client_addr, server_addr):
        self.conn = conn
        self.target = target            # a Symbol, or VERSION
        self.length = length
        self.mode = mode
        self.cycle = cycle              # 100 ns
        self.client_addr = client_addr  # (net id bytes, port) of the client
        self.server_addr = server_addr  # (net id bytes, port) the client addressed
        self.last = None
        self.task = None


class Plc:
    def __init__(self, handle_base, task_cycle=0.01):
        self.task_cycle = task_cycle    # s, the PLC task that looks at notifications
        self.symbols = {}
        self.by_addr = {}
        self.handles = {}              # handle -> (symbol, connection that took it)
        self.version = 1
        self.ads_state = 5
        self.device_state = 0
        self.next_handle = handle_base
        self.next_note = handle_base + 1000000
        self.next_offset = 1000
        self.conns = set()
        self.frames = []
        self.record = True
        self.stats = {}
        self.sum_limit = None
        self.muted = False
        self.hold = 0
        self.held = []
        self.waiters = []
        self.report = None             # the event writer while `report on'
        self.nc = Nc()                 # the NC on AMS port 500

    def wake(self):
        """Answers `wait_clients' and `wait_stat' commands whose condition holds."""
        for waiter in list(self.waiters):
            if waiter.holds(self):
                self.waiters.remove(waiter)
                waiter.answer("ok")

    def count(self, key, n=1):
        self.stats[key] = self.stats.get(key, 0) + n
        if self.waiters:
            self.wake()

    # --- symbols -------------------------------------------------------------------

    def add(self, name, type_name, ads_type, size, value, nested=False):
        offset = self.next_offset
        self.next_offset += max(size, 1) + 16
        sym = Symbol(name, type_name, ads_type, size, value, IG_PLC_DATA, offset, nested)
        self.symbols[name.upper()] = sym
        self.by_addr[(sym.group, sym.offset)] = sym
        return sym

    def lookup(self, name):
        return self.symbols.get(name.upper())

    def drop_symbol(self, sym):
        del self.symbols[sym.name.upper()]
        del self.by_addr[(sym.group, sym.offset)]
        self.handles = {h: v for h, v in self.handles.items() if v[0] is not sym}
        for conn in self.conns:
            for nh in [nh for nh, n in conn.notes.items() if n.target is sym]:
                conn.drop_note(nh)

    def restart(self):
        self.handles = {}
        for conn in self.conns:
            for nh in [nh for nh, n in conn.notes.items() if n.target is not VERSION]:
                conn.drop_note(nh)
        for sym in self.symbols.values():
            sym.value[:] = sym.initial
        self.program_changed()

    def program_changed(self):
        self.version = (self.version + 1) % 256
        self.changed(VERSION, filetime_now())

    def table(self):
        return b"".join(s.entry() for s in self.symbols.values() if not s.nested)

    # --- values and notifications --------------------------------------------------

    def set_value(self, sym, data, stamp):
        sym.value[: len(data)] = data
        self.changed(sym, stamp)

    def changed(self, target, stamp):
        for conn in list(self.conns):
            samples = conn.collect([target])
            if samples:
                conn.send_samples([(stamp, samples)])

    def burst(self, groups):
        """groups: [(stamp, [(sym, data)])] in order: the values of each stamp are
        taken as they were then, and each connection gets them all in one frame."""
        per_conn = {conn: [] for conn in self.conns}
        for stamp, pairs in groups:
            for sym, data in pairs:
                sym.value[: len(data)] = data
            for conn, stamps in per_conn.items():
                samples = conn.collect([sym for sym, _ in pairs])
                if samples:
                    stamps.append((stamp, samples))
        for conn, stamps in per_conn.items():
            if stamps:
                conn.send_samples(stamps)


class Conn(asyncio.Protocol):
    def __init__(self, plc):
        self.plc = plc
        self.buf = b""
        self.notes = {}
        self.transport = None

    def connection_made(self, transport):
        self.transport = transport
        sock = transport.get_extra_info("socket")
        if sock is not None:
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.plc.conns.add(self)
        self.plc.count("connections")
        self.plc.wake()

    def connection_lost(self, exc):
        self.plc.conns.discard(self)
        for nh in list(self.notes):
            self.drop_note(nh)
        # What a closed connection held goes, as when TwinCAT's router drops a client.
        self.plc.handles = {h: v for h, v in self.plc.handles.items() if v[1] is not self}
        self.plc.wake()

    def data_received(self, data):
        self.buf += data
        out = []
        while len(self.buf) >= 6:
            reserved, length = struct.unpack_from("<HI", self.buf, 0)
            if reserved != 0 or length < 32 or length > 16 * 1024 * 1024:
                sys.stderr.write("fake_plc: malformed frame, closing the connection\n")
                self.transport.close()
                return
            if len(self.buf) < 6 + length:
                break
            frame, self.buf = self.buf[: 6 + length], self.buf[6 + length:]
            answer = self.request(frame)
            if answer is None:
                continue
            plc = self.plc
            if plc.hold:
                plc.held.append((self, answer))
                if len(plc.held) >= plc.hold:
                    plc.hold = 0
                    for conn, data in plc.held:
                        conn.transport.write(data)
                    plc.held = []
            else:
                out.append(answer)
        if out:
            self.transport.write(b"".join(out))

    def request(self, frame):
        plc = self.plc
        if plc.record:
            plc.frames.append(frame)
        tnet, tport, snet, sport, cmd, flags, length, _err, invoke = \
            AMS_HEADER.unpack_from(frame, 6)
        data = frame[38:]
        if flags & 1 or len(data) != length:
            return None
        plc.count("requests")
        if plc.muted:
            return None
        client, server = (snet, sport), (tnet, tport)
        try:
            result, after = self.dispatch(cmd, data, client, server)
        except struct.error:
            result, after = struct.pack("<I", ERR_SIZE), None
        header = AMS_HEADER.pack(snet, sport, tnet, tport, cmd, 0x0005, len(result), 0, invoke)
        if after is not None:
            asyncio.get_running_loop().call_soon(after)
        return TCP_HEADER.pack(0, 32 + len(result)) + header + result

    def dispatch(self, cmd, data, client, server):
        plc = self.plc
        if server[1] == NC_PORT and cmd in (2, 3):
            return self.nc_dispatch(cmd, data)
        if server[1] == SYSTEM_SERVICE_PORT and cmd == 9:
            return self.file_dispatch(data)
        if cmd == 1:
            plc.count("device_info")
            return struct.pack("<IBBH16s", 0, 3, 1, 4024, b"Fake PLC"), None
        if cmd == 2:
            group, offset, length = struct.unpack_from("<III", data)
            err, value = self.read(group, offset, length)
            return struct.pack("<II", err, len(value)) + value, None
        if cmd == 3:
            group, offset, length = struct.unpack_from("<III", data)
            payload = data[12: 12 + length]
            if len(payload) != length:
                return struct.pack("<I", ERR_SIZE), None
            return struct.pack("<I", self.write(group, offset, payload)), None
        if cmd == 4:
            plc.count("read_state")
            return struct.pack("<IHH", 0, plc.ads_state, plc.device_state), None
        if cmd == 5:
            state, dev, _length = struct.unpack_from("<HHI", data)
            plc.ads_state, plc.device_state = state, dev
            plc.count("write_control")
            return struct.pack("<I", 0), None
        if cmd == 6:
            group, offset, length, mode, _delay, cycle = struct.unpack_from("<IIIIII", data)
            err, nh, after = self.add_note(group, offset, length, mode, cycle, client, server)
            return struct.pack("<II", err, nh), after
        if cmd == 7:
            (nh,) = struct.unpack_from("<I", data)
            if nh not in self.notes:
                return struct.pack("<I", ERR_NOTE_HANDLE), None
            self.drop_note(nh)
            plc.count("notes_deleted")
            return struct.pack("<I", 0), None
        if cmd == 9:
            group, offset, rlen, wlen = struct.unpack_from("<IIII", data)
            wdata = data[16: 16 + wlen]
            if len(wdata) != wlen:
                return struct.pack("<II", ERR_SIZE, 0), None
            err, value = self.read_write(group, offset, rlen, wdata)
            return struct.pack("<II", err, len(value)) + value, None
        return struct.pack("<I", ERR_SERVICE), None

    def nc_dispatch(self, cmd, data):
        nc = self.plc.nc
        if cmd == 2:
            self.plc.count("nc_reads")
            group, offset, length = struct.unpack_from("<III", data)
            err, value = nc.read(group, offset, length)
            return struct.pack("<II", err, len(value)) + value, None
        group, offset, length = struct.unpack_from("<III", data)
        payload = data[12: 12 + length]
        if len(payload) != length:
            return struct.pack("<I", ERR_SIZE), None
        return struct.pack("<I", nc.write(group, offset, payload)), None

    def file_dispatch(self, data):
        """The system service's files: FOPEN (read-write: the name in, a handle out),
        FWRITE and FCLOSE (read-write by handle), as ADS clients use them."""
        files = self.plc.nc.files
        group, offset, rlen, wlen = struct.unpack_from("<IIII", data)
        wdata = data[16: 16 + wlen]
        if len(wdata) != wlen:
            return struct.pack("<II", ERR_SIZE, 0), None
        self.plc.count("file_requests")
        if group == IG_FOPEN:
            if not offset & FOPEN_WRITE or offset >> 16 != PATH_GENERIC or rlen < 4:
                return struct.pack("<II", ERR_INVALID_DATA, 0), None
            name = wdata.split(b"\0", 1)[0].decode("latin-1")
            handle = files.open(name)
            return struct.pack("<III", 0, 4, handle), None
        if group == IG_FWRITE:
            if not files.write(offset, wdata):
                return struct.pack("<II", ERR_INVALID_DATA, 0), None
            return struct.pack("<II", 0, 0), None
        if group == IG_FCLOSE:
            if not files.close(offset):
                return struct.pack("<II", ERR_INVALID_DATA, 0), None
            return struct.pack("<II", 0, 0), None
        return struct.pack("<II", ERR_GROUP, 0), None

    # --- the index groups ------------------------------------------------------------

    def target_of(self, group, offset):
        if group == IG_VALBYHND:
            return self.plc.handles.get(offset, (None,))[0], ERR_SYMBOL
        if group == IG_PLC_DATA:
            return self.plc.by_addr.get((group, offset)), ERR_OFFSET
        return None, ERR_GROUP

    def read(self, group, offset, length):
        plc = self.plc
        plc.count("reads")
        if group == IG_VALBYHND:     # the usual case first: a value by handle
            entry = plc.handles.get(offset)
            if entry is None:
                return ERR_SYMBOL, b""
            return 0, bytes(entry[0].value[:length])
        if group == IG_VERSION:
            return 0, bytes([plc.version])[:length]
        if group == IG_UPLOADINFO:
            return 0, struct.pack("<II", len([s for s in plc.symbols.values() if not s.nested]),
                                  len(plc.table()))[:length]
        if group == IG_UPLOADINFO2:
            count = len([s for s in plc.symbols.values() if not s.nested])
            return 0, struct.pack("<IIIIII", count, len(plc.table()), 0, 0, 0, 0)[:length]
        if group == IG_UPLOAD:
            table = plc.table()
            if length < len(table):
                return ERR_SIZE, b""
            plc.count("uploads")
            return 0, table
        sym, err = self.target_of(group, offset)
        if sym is None:
            return err, b""
        # Asked for more than the symbol holds, TwinCAT answers what it holds (the
        # answer carries its length): pyads reads strings into a 1 KiB buffer.
        return 0, bytes(sym.value[:length])

    def write(self, group, offset, payload):
        plc = self.plc
        plc.count("writes")
        if group == IG_RELEASEHND:
            if len(payload) != 4:
                return ERR_SIZE
            (h,) = struct.unpack("<I", payload)
            if self.plc.handles.pop(h, None) is None:
                return ERR_SYMBOL
            plc.count("released")
            return 0
        sym, err = self.target_of(group, offset)
        if sym is None:
            return err
        if len(payload) > max(sym.size, 1):
            return ERR_SIZE
        plc.set_value(sym, payload, filetime_now())
        if plc.report is not None:
            plc.report(("notification", "written", sym.name.encode("latin-1"),
                        bytes(sym.value)))
        return 0

    def read_write(self, group, offset, rlen, wdata):
        plc = self.plc
        if group in (IG_HNDBYNAME, IG_INFOBYNAMEEX):
            name = wdata.split(b"\0", 1)[0].decode("latin-1")
            sym = plc.lookup(name)
            if sym is None:
                return ERR_SYMBOL, b""
            if group == IG_HNDBYNAME:
                if rlen < 4:
                    return ERR_SIZE, b""
                h = plc.next_handle
                plc.next_handle += 1
                plc.handles[h] = (sym, self)
                plc.count("acquired")
                return 0, struct.pack("<I", h)
            entry = sym.entry()
            if rlen < len(entry):
                return ERR_SIZE, b""
            plc.count("infos")
            return 0, entry
        if group in (IG_SUM_READ, IG_SUM_WRITE, IG_SUM_READWRITE):
            if plc.sum_limit is not None and offset > plc.sum_limit:
                return ERR_SIZE, b""
            plc.count("sums")
            plc.count("sub_commands", offset)
            return self.sum(group, offset, rlen, wdata)
        return ERR_GROUP, b""

    def sum(self, group, n, rlen, wdata):
        if group == IG_SUM_READ:
            items = [struct.unpack_from("<III", wdata, 12 * i) for i in range(n)]
            errs, datas = [], []
            for g, o, length in items:
                err, value = self.read(g, o, length)
                errs.append(err)
                datas.append(value.ljust(length, b"\0"))
            out = struct.pack("<%dI" % n, *errs) + b"".join(datas)
        elif group == IG_SUM_WRITE:
            items = [struct.unpack_from("<III", wdata, 12 * i) for i in range(n)]
            pos, errs = 12 * n, []
            for g, o, length in items:
                errs.append(self.write(g, o, wdata[pos: pos + length]))
                pos += length
            out = struct.pack("<%dI" % n, *errs)
        else:
            items = [struct.unpack_from("<IIII", wdata, 16 * i) for i in range(n)]
            pos, heads, datas = 16 * n, [], []
            for g, o, length, wl in items:
                err, value = self.read_write(g, o, length, wdata[pos: pos + wl])
                pos += wl
                heads.append(struct.pack("<II", err, len(value)))
                datas.append(value)
            out = b"".join(heads) + b"".join(datas)
        if len(out) > rlen:
            return ERR_SIZE, b""
        return 0, out

    # --- notifications -------------------------------------------------------------

    def add_note(self, group, offset, length, mode, cycle, client, server):
        plc = self.plc
        if group == IG_VERSION:
            target, size = VERSION, 1
        else:
            target, err = self.target_of(group, offset)
            if target is None:
                return err, 0, None
            size = max(target.size, 1)
        if length > size or length == 0:
            return ERR_SIZE, 0, None
        if mode not in (MODE_CYCLIC, MODE_ON_CHANGE):
            return ERR_TRANSMODE, 0, None
        nh = plc.next_note
        plc.next_note += 1
        note = Note(self, target, length, mode, cycle, client, server)
        self.notes[nh] = note
        plc.count("notes_added")
        if mode == MODE_CYCLIC:
            note.task = asyncio.get_running_loop().create_task(self.cyclic(nh, note))
            return 0, nh, None
        # TwinCAT sends the present value of an on-change notification in the first
        # cycle after adding it (not before the answer: AdsLib must know the handle).
        delay = max(cycle / 1e7, plc.task_cycle)
        return 0, nh, lambda: asyncio.get_running_loop().call_later(delay, self.send_first, nh)

    def drop_note(self, nh):
        note = self.notes.pop(nh, None)
        if note is not None and note.task is not None:
            note.task.cancel()

    def send_first(self, nh):
        note = self.notes.get(nh)
        if note is not None:
            note.last = self.value_of(note)
            self.send_samples([(filetime_now(), [(nh, note, note.last)])])

    def value_of(self, note):
        if note.target is VERSION:
            return bytes([self.plc.version])
        return bytes(note.target.value[: note.length])

    async def cyclic(self, nh, note):
        period = max(note.cycle / 1e7, self.plc.task_cycle)
        while True:
            self.send_samples([(filetime_now(), [(nh, note, self.value_of(note))])])
            await asyncio.sleep(period)

    def collect(self, targets):
        """Samples of this connection's on-change notifications on these targets whose
        value moved since the last one sent."""
        samples = []
        for nh, note in self.notes.items():
            if note.mode != MODE_ON_CHANGE or not any(note.target is t for t in targets):
                continue
            value = self.value_of(note)
            if value != note.last:
                note.last = value
                samples.append((nh, note, value))
        return samples

    def send_samples(self, stamps):
        """One frame per (client, server) address pair, each with all its stamps."""
        frames = {}
        for stamp, samples in stamps:
            for nh, note, value in samples:
                key = (note.client_addr, note.server_addr)
                per = frames.setdefault(key, {})
                per.setdefault(stamp, []).append((nh, value))
        for (client, server), per in frames.items():
            body = struct.pack("<I", len(per))
            for stamp, samples in per.items():
                body += struct.pack("<QI", stamp, len(samples))
                for nh, value in samples:
                    body += struct.pack("<II", nh, len(value)) + value
            payload = struct.pack("<I", len(body)) + body
            header = struct.pack("<6sH6sHHHIII", client[0], client[1], server[0], server[1],
                                 8, 0x0004, len(payload), 0, 0)
            self.plc.count("notifications_sent")
            self.transport.write(struct.pack("<HI", 0, 32 + len(payload)) + header + payload)


# --- an NC with axes, on AMS port 500 ------------------------------------------------

NC_PORT = 500
SYSTEM_SERVICE_PORT = 10000
IG_FOPEN, IG_FCLOSE, IG_FWRITE = 120, 121, 123
FOPEN_WRITE = 0x2
PATH_GENERIC = 1
IG_NCI_STATE = 0x2100
IG_NCI_FUNCTIONS = 0x2200
IG_NCI_CYCLIC = 0x2300
NCI_OVERRIDE = 0x2             # the channel's path override, UINT32, 1000000 = 100 %
# The interpreter's states as the NC numbers them.
ITP_IDLE, ITP_READY, ITP_RUNNING, ITP_ABORTED = 1, 2, 5, 12
NCI_NO_PROGRAM = 0x4101         # the fake's own codes for a program it cannot run
NCI_BAD_PROGRAM = 0x4102
NCI_AXIS_NOT_READY = 0x4103
IG_NC_STATE = 0x4100
IG_NC_FUNCTIONS = 0x4200
IG_NC_CYCLIC = 0x4300
ONLINE_SIZE = 256
# The fake's own answers to a start it cannot take (a real NC has its own codes).
NC_NOT_READY = 0x4260
NC_BEYOND_LIMITS = 0x4358
NC_BAD_PARAMETER = 0x4221
ERR_INVALID_DATA = 0x706
START_ABSOLUTE = 1              # the start type of an absolute move
POSITION_ABSOLUTE = 1           # the type of an absolute actual position
NC_DEFAULT_ACC = 1000.0         # the axis's own acceleration and deceleration
STEP = 0.001                    # s, the model's integration step
QUICK_STOP = 1e9                # the deceleration of a stop on a fault: at once


class NcAxis:
    """An NC axis: disabled, standing, moving, homing, stopping or in error. A move
    accelerates, runs at its velocity times the override and brakes so as to stand
    at its target (a trapezoid, jerk ignored)."""

    def __init__(self, axis_id, limits=None, home_s=0.1):
        self.id = axis_id
        self.limits = limits
        self.home_s = home_s
        self.enables = [0, 0, 0]       # controller, feed plus, feed minus
        self.override = 1000000
        self.pos = 0.0
        self.vel = 0.0
        self.job = None                # None | "move" | "stop" | "home"
        self.target = 0.0
        self.vmax = self.acc = self.dec = 0.0
        self.start = 0.0
        self.home_end = 0.0
        self.referenced = False
        self.error = 0
        self.fail_next = None          # the code the next move faults with
        self.fail = None               # (code, position where it faults)
        self.t = time.monotonic()

    def enabled(self):
        return self.enables[0] != 0 and self.enables[1] != 0 and self.enables[2] != 0

    def advance(self):
        now = time.monotonic()
        while self.t < now:
            dt = min(STEP, now - self.t)
            self.t += dt
            self.step(dt)
        self.t = now

    def step(self, dt):
        if self.job == "home":
            if self.t >= self.home_end:
                self.referenced = True
                self.job = None
        elif self.job == "stop":
            speed = abs(self.vel) - self.dec * dt
            if speed <= 0:
                self.vel, self.job = 0.0, None
            else:
                self.vel = speed if self.vel > 0 else -speed
                self.pos += self.vel * dt
        elif self.job == "move":
            self.move_step(dt)

    def move_step(self, dt):
        dist = self.target - self.pos
        way = 1.0 if dist >= 0 else -1.0
        speed = self.vel * way                 # towards the target
        if speed < 0:                          # still going the other way: brake
            speed = min(0.0, speed + self.dec * dt)
        else:
            cap = self.vmax * self.override / 1000000
            if speed > cap:
                speed = max(cap, speed - self.dec * dt)
            else:
                speed = min(cap, speed + self.acc * dt)
            speed = min(speed, (2 * self.dec * abs(dist)) ** 0.5)
        # There (a move to where the axis stands is done at once, as on a real NC).
        if dist == 0 or (speed > 0 and speed * dt >= abs(dist)):
            self.pos, self.vel, self.job = self.target, 0.0, None
            return
        self.vel = speed * way
        self.pos += self.vel * dt
        if self.fail is not None and (self.pos - self.fail[1]) * way >= 0:
            self.fault(self.fail[0])

    def fault(self, code):
        self.error = code
        self.job = None
        self.vel = 0.0
        self.fail = None

    def status(self):
        moving = self.vel != 0.0
        bits = 0
        if self.enabled() and self.error == 0:
            bits |= 1 << 0
        if self.referenced:
            bits |= 1 << 1
        if not moving:
            bits |= 1 << 2
        if self.job is None and not moving:
            bits |= 1 << 4
        if self.job is not None:
            bits |= 1 << 8
        if self.job == "home":
            bits |= 1 << 11
        if self.enabled():
            bits |= 1 << 20
        if self.error:
            bits |= 1 << 31
        return bits

    def online(self):
        data = struct.pack("<ii6dII5dIIII", self.error, 0, self.pos, self.pos, self.pos,
                           self.pos, self.vel, self.vel, self.override, 0,
                           0.0, 0.0, 0.0, 0.0, 0.0, self.status(), 0, 0, 0)
        return data.ljust(ONLINE_SIZE, b"\0")

    def ready(self):
        return self.enabled() and self.error == 0

    # --- functions (0x4200 + id) ------------------------------------------------------

    def function(self, offset, data):
        if offset == 0x1:              # reset
            self.error = 0
            self.job = None
            self.vel = 0.0
            return 0
        if offset == 0x2:              # stop with the NC's own deceleration
            return self.stop(self.dec or 1000.0)
        if offset == 0x4:              # stop {deceleration, jerk}
            dec, _jerk = struct.unpack_from("<dd", data)
            if dec <= 0:
                return NC_BAD_PARAMETER
            return self.stop(dec)
        if offset == 0x10:             # reference (homing)
            if not self.ready():
                return NC_NOT_READY
            self.referenced = False
            self.job = "home"
            self.vel = 0.0
            self.home_end = self.t + self.home_s
            return 0
        if offset == 0x21:             # extended start: {type, reserved, target, velocity,
            #                            then {use the NC's own?, reserved, value} for the
            #                            acceleration, the deceleration and the jerk}
            if len(data) < 72:
                return ERR_SIZE
            (start_type, _res, target, v, own_acc, _r1, acc, own_dec, _r2, dec,
             _own_jerk, _r3, _jerk) = struct.unpack_from("<IIddIIdIIdIId", data)
            if start_type != START_ABSOLUTE:
                return NC_BAD_PARAMETER
            acc = NC_DEFAULT_ACC if own_acc else acc
            dec = NC_DEFAULT_ACC if own_dec else dec
            if not self.ready():
                return NC_NOT_READY
            if min(v, acc, dec) <= 0:
                return NC_BAD_PARAMETER
            if self.limits is not None and not self.limits[0] <= target <= self.limits[1]:
                return NC_BEYOND_LIMITS
            self.job, self.target, self.vmax, self.acc, self.dec = "move", target, v, acc, dec
            self.fail = None
            if self.fail_next is not None:
                self.fail = (self.fail_next, (self.pos + target) / 2)
                self.fail_next = None
            return 0
        if offset == 0x1A:             # set actual position {type, reserved, position}
            if len(data) < 16:
                return ERR_SIZE
            pos_type, _res, pos = struct.unpack_from("<IId", data)
            if pos_type != POSITION_ABSOLUTE:
                return NC_BAD_PARAMETER
            self.pos = pos
            return 0
        return ERR_OFFSET

    def stop(self, dec):
        if self.error:
            return NC_NOT_READY
        self.job = "stop" if self.vel != 0.0 else None
        self.dec = dec
        return 0

    # --- the cyclic interface (0x4300 + id) --------------------------------------------

    def cyclic(self, offset, data):
        if offset in (0x2, 0x3, 0x4):
            (value,) = struct.unpack_from("<H", data)
            self.enables[offset - 2] = value
            if not self.enabled() and self.job is not None:
                # The drive lets go: what ran stops where it is.
                self.job, self.vel = None, 0.0
            return 0
        if offset == 0x21:
            (value,) = struct.unpack_from("<I", data)
            if value > 1000000:
                return ERR_INVALID_DATA
            self.override = value
            return 0
        return ERR_OFFSET

    def describe(self):
        return {"position": self.pos, "velocity": self.vel,
                "override": self.override, "error": self.error,
                "enabled": self.enabled(), "referenced": self.referenced,
                "job": self.job or "none"}


class Files:
    """The target's files, as the system service opens, writes and closes them."""

    def __init__(self):
        self.files = {}
        self.open_files = {}            # handle -> (name, bytes so far)
        self.next_handle = 1

    def open(self, name):
        handle = self.next_handle
        self.next_handle += 1
        self.open_files[handle] = (name, b"")
        return handle

    def write(self, handle, data):
        if handle not in self.open_files:
            return False
        name, body = self.open_files[handle]
        self.open_files[handle] = (name, body + data)
        return True

    def close(self, handle):
        if handle not in self.open_files:
            return False
        name, body = self.open_files.pop(handle)
        self.files[name] = body
        return True


class NciChannel:
    """An NC I channel: its interpreter loads a DIN 66025 program by name (lines G01,
    arcs G02/G03 with I and J, in the XY plane, absolute, feed F in mm/min) and runs
    it, its axes following the path at the feed times the channel's override. A
    program ends READY; one that faults (nc_channel_fail) stops its axes halfway,
    ABORTED with the channel's error, until a reset."""

    def __init__(self, channel_id, axes):
        self.id = channel_id
        self.axes = axes                # NcAxis, X Y [Z]
        self.state = ITP_IDLE
        self.error = 0
        self.loaded = ""
        self.program = None             # the path: [(kind, start, end, centre, feed)]
        self.runs = 0
        self.fail_next = None
        self.fail_at = None
        self.along = 0.0
        self.override = 1000000
        self.t = time.monotonic()

    def read(self, offset, length):
        self.advance()
        if offset == 1:
            return 0, struct.pack("<i", self.error)[:length]
        if offset == 3:
            return 0, struct.pack("<I", self.state)[:length]
        if offset == 7:
            return 0, self.loaded.encode("latin-1")[:100].ljust(length, b"\0")[:length]
        return ERR_OFFSET, b""

    def function(self, offset, data, files):
        self.advance()
        if offset == 0x4:               # load by name
            name = data.split(b"\0", 1)[0].decode("latin-1")
            if self.state == ITP_RUNNING:
                return NCI_AXIS_NOT_READY
            if name not in files.files:
                self.error = NCI_NO_PROGRAM
                return NCI_NO_PROGRAM
            program = parse_din(files.files[name].decode("latin-1"), self.position())
            if program is None:
                self.error = NCI_BAD_PROGRAM
                return NCI_BAD_PROGRAM
            self.loaded, self.program, self.state = name, program, ITP_READY
            return 0
        if offset == 0x2:               # start the interpreter
            if self.state != ITP_READY or self.program is None or self.error:
                return NCI_AXIS_NOT_READY
            if not all(a.ready() and a.job is None for a in self.axes):
                return NCI_AXIS_NOT_READY
            self.state, self.along, self.runs = ITP_RUNNING, 0.0, self.runs + 1
            self.fail_at = None
            if self.fail_next is not None:
                self.fail_at = (self.fail_next, path_length(self.program) / 2)
                self.fail_next = None
            return 0
        if offset == 0x10:              # reset
            self.error, self.state, self.program = 0, ITP_IDLE, None
            for a in self.axes:
                a.vel = 0.0
            return 0
        if offset == 0x11:              # stop: the axes stand where they are
            if self.state == ITP_RUNNING:
                self.state = ITP_IDLE
            for a in self.axes:
                a.vel = 0.0
            return 0
        return ERR_OFFSET

    def cyclic(self, offset, data):
        """The cyclic interface (0x2300 + id): the path override."""
        if offset != NCI_OVERRIDE:
            return ERR_OFFSET
        self.advance()
        (value,) = struct.unpack_from("<I", data)
        if value > 1000000:
            return ERR_INVALID_DATA
        self.override = value
        return 0

    def position(self):
        return tuple(a.pos for a in self.axes) + (0.0,) * (3 - len(self.axes))

    def advance(self):
        now = time.monotonic()
        dt, self.t = now - self.t, now
        if self.state != ITP_RUNNING:
            return
        override = self.override / 1000000
        self.along += dt * override * self.feed_at(self.along)
        total = path_length(self.program)
        if self.fail_at is not None and self.along >= self.fail_at[1]:
            self.along = self.fail_at[1]
            self.place(self.along, 0.0)
            self.error, self.state, self.fail_at = self.fail_at[0], ITP_ABORTED, None
            return
        if self.along >= total:
            self.place(total, 0.0)
            self.state = ITP_READY
            return
        self.place(self.along, self.feed_at(self.along) * override)

    def feed_at(self, along):
        for seg in self.program:
            if along < seg["s"] + seg["len"]:
                return seg["feed"]
        return self.program[-1]["feed"]

    def place(self, along, speed):
        point = path_point(self.program, along)
        for i, a in enumerate(self.axes):
            a.pos, a.vel = point[i], speed

    def describe(self):
        self.advance()
        return {"state": self.state, "error": self.error,
                "loaded": self.loaded.encode("latin-1"), "runs": self.runs,
                "along": self.along, "override": self.override}


def parse_din(text, start):
    """A DIN 66025 program's path: absolute X Y Z, G01 lines and G02/G03 arcs (I J
    the centre from the segment's start), F the feed in mm/min, modal; None for a
    word the fake does not know."""
    segs, here, feed, s = [], start, None, 0.0
    for raw in text.splitlines():
        line = raw.split(";", 1)[0].strip()
        if not line:
            continue
        words = line.split()
        g = None
        coords = {}
        for w in words:
            letter, value = w[0].upper(), w[1:]
            try:
                if letter == "N":
                    continue
                if letter == "G":
                    code = int(value)
                    if code in (1, 2, 3):
                        g = code
                    elif code not in (17, 71, 90):
                        return None
                elif letter == "M":
                    if int(value) not in (2, 30):
                        return None
                elif letter in "XYZIJF":
                    coords[letter] = float(value)
                else:
                    return None
            except ValueError:
                return None
        if "F" in coords:
            feed = coords["F"] / 60.0
        if g is None:
            continue
        if feed is None or feed <= 0:
            return None
        end = (coords.get("X", here[0]), coords.get("Y", here[1]), coords.get("Z", here[2]))
        if g == 1:
            length = math.dist(here, end)
            segs.append({"kind": 1, "start": here, "end": end, "s": s, "len": length,
                         "feed": feed})
        else:
            centre = (here[0] + coords.get("I", 0.0), here[1] + coords.get("J", 0.0))
            r = math.dist(here[:2], centre)
            if r <= 0:
                return None
            a0 = math.atan2(here[1] - centre[1], here[0] - centre[0])
            a1 = math.atan2(end[1] - centre[1], end[0] - centre[0])
            sweep = a1 - a0
            if g == 3:                  # counter-clockwise
                while sweep <= 1e-12:
                    sweep += 2 * math.pi
            else:
                while sweep >= -1e-12:
                    sweep -= 2 * math.pi
            length = abs(sweep) * r
            segs.append({"kind": g, "start": here, "end": end, "s": s, "len": length,
                         "feed": feed, "centre": centre, "r": r, "a0": a0, "sweep": sweep})
        s += length
        here = end
    return segs if segs else None


def path_length(segs):
    return segs[-1]["s"] + segs[-1]["len"]


def path_point(segs, along):
    for seg in segs:
        if along <= seg["s"] + seg["len"]:
            f = 0.0 if seg["len"] == 0 else (along - seg["s"]) / seg["len"]
            z = seg["start"][2] + f * (seg["end"][2] - seg["start"][2])
            if seg["kind"] == 1:
                return tuple(seg["start"][i] + f * (seg["end"][i] - seg["start"][i])
                             for i in range(2)) + (z,)
            angle = seg["a0"] + f * seg["sweep"]
            return (seg["centre"][0] + seg["r"] * math.cos(angle),
                    seg["centre"][1] + seg["r"] * math.sin(angle), z)
    return segs[-1]["end"]


class Nc:
    def __init__(self):
        self.axes = {}
        self.channels = {}
        self.files = Files()

    def axis(self, group, base):
        axis = self.axes.get(group - base)
        if axis is not None:
            axis.advance()
        return axis

    def channel(self, group, base):
        channel = self.channels.get(group - base)
        if channel is not None:
            for a in channel.axes:
                a.advance()
        return channel

    def read(self, group, offset, length):
        if IG_NC_STATE < group <= IG_NC_STATE + 0xFF:
            axis = self.axis(group, IG_NC_STATE)
            if axis is None:
                return ERR_GROUP, b""
            for channel in self.channels.values():
                if axis in channel.axes:
                    channel.advance()
            if offset == 0:
                return 0, axis.online()[:length]
            if offset == 1:
                return 0, struct.pack("<I", axis.error)[:length]
            return ERR_OFFSET, b""
        if IG_NCI_STATE < group <= IG_NCI_STATE + 0xFF:
            channel = self.channel(group, IG_NCI_STATE)
            if channel is None:
                return ERR_GROUP, b""
            return channel.read(offset, length)
        return ERR_GROUP, b""

    def write(self, group, offset, data):
        if IG_NCI_FUNCTIONS < group <= IG_NCI_FUNCTIONS + 0xFF:
            channel = self.channel(group, IG_NCI_FUNCTIONS)
            if channel is None:
                return ERR_GROUP
            return channel.function(offset, data, self.files)
        if IG_NCI_CYCLIC < group <= IG_NCI_CYCLIC + 0xFF:
            channel = self.channel(group, IG_NCI_CYCLIC)
            if channel is None:
                return ERR_GROUP
            try:
                return channel.cyclic(offset, data)
            except struct.error:
                return ERR_SIZE
        for base, handler in ((IG_NC_FUNCTIONS, NcAxis.function),
                              (IG_NC_CYCLIC, NcAxis.cyclic)):
            if base < group <= base + 0xFF:
                axis = self.axis(group, base)
                if axis is None:
                    return ERR_GROUP
                try:
                    return handler(axis, offset, data)
                except struct.error:
                    return ERR_SIZE
        return ERR_GROUP


# --- control ---------------------------------------------------------------------------


class Waiter:
    """A `wait_clients' or `wait_stat' command waiting for its condition."""

    def __init__(self, holds, answer):
        self.holds = holds
        self.answer = answer


def control(plc, line, loop, answer):
    words = line.split()
    if not words:
        return None
    cmd, args = words[0], [unquote(w) for w in words[1:]]
    try:
        if cmd == "add":
            nested = len(args) > 5 and args[5] == "nested"
            sym = plc.add(args[0], args[1], int(args[2]), int(args[3]), bytes.fromhex(args[4]),
                          nested)
            return ("ok", sym.group, sym.offset)
        if cmd == "set":
            sym = plc.lookup(args[0])
            if sym is None:
                return ("error", "unknown_symbol")
            plc.set_value(sym, bytes.fromhex(args[1]), filetime_now())
            return "ok"
        if cmd == "burst":
            groups = []
            for part in " ".join(args).split(";"):
                ws = part.split()
                pairs = [(plc.lookup(ws[i]), bytes.fromhex(ws[i + 1]))
                         for i in range(1, len(ws), 2)]
                groups.append((int(ws[0]), pairs))
            plc.burst(groups)
            return "ok"
        if cmd == "get":
            sym = plc.lookup(args[0])
            if sym is None:
                return ("error", "unknown_symbol")
            return ("ok", bytes(sym.value))
        if cmd == "remove":
            plc.drop_symbol(plc.lookup(args[0]))
            plc.program_changed()
            return "ok"
        if cmd == "retype":
            plc.drop_symbol(plc.lookup(args[0]))
            plc.add(args[0], args[1], int(args[2]), int(args[3]), bytes.fromhex(args[4]))
            plc.program_changed()
            return "ok"
        if cmd == "restart":
            plc.restart()
            return "ok"
        if cmd == "bump":
            plc.program_changed()
            return "ok"
        if cmd == "limit":
            plc.sum_limit = int(args[0])
            return "ok"
        if cmd == "frames":
            return ("ok", list(plc.frames))
        if cmd == "stats":
            stats = dict(plc.stats)
            stats["handles"] = len(plc.handles)
            stats["notes"] = sum(len(c.notes) for c in plc.conns)
            stats["clients"] = len(plc.conns)
            stats["version"] = plc.version
            return ("ok", stats)
        if cmd == "clear":
            plc.frames = []
            plc.stats = {}
            return "ok"
        if cmd == "record":
            plc.record = args[0] == "on"
            return "ok"
        if cmd == "report":
            plc.report = answer if args[0] == "on" else None
            return "ok"
        if cmd == "hold":
            plc.hold = int(args[0])
            return "ok"
        if cmd == "mute":
            plc.muted = True
            return "ok"
        if cmd == "stall":
            for conn in list(plc.conns):
                conn.transport.get_extra_info("socket").setsockopt(
                    socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
                conn.transport.pause_reading()
            return "ok"
        if cmd == "unstall":
            for conn in list(plc.conns):
                if not conn.transport.is_closing():
                    conn.transport.resume_reading()
            return "ok"
        if cmd == "unmute":
            plc.muted = False
            return "ok"
        if cmd in ("wait_clients", "wait_stat"):
            if cmd == "wait_clients":
                n = int(args[0])
                waiter = Waiter(lambda p: len(p.conns) == n, answer)
            else:
                key, n = args[0], int(args[1])
                waiter = Waiter(lambda p: p.stats.get(key, 0) >= n, answer)
                args = args[1:]
            if waiter.holds(plc):
                return "ok"
            plc.waiters.append(waiter)

            def expire():
                if waiter in plc.waiters:
                    plc.waiters.remove(waiter)
                    waiter.answer(("error", "timeout"))

            loop.call_later(int(args[1]) / 1000, expire)
            return None
        if cmd == "drop":
            for conn in list(plc.conns):
                conn.transport.close()
            return "ok"
        if cmd == "garbage":
            for conn in list(plc.conns):
                conn.transport.write(bytes.fromhex(args[0]))
            return "ok"
        if cmd == "nc_axis":
            axis_id = int(args[0])
            limits = (float(args[1]), float(args[2])) if len(args) >= 3 else None
            home_s = int(args[3]) / 1000 if len(args) >= 4 else 0.1
            plc.nc.axes[axis_id] = NcAxis(axis_id, limits, home_s)
            return "ok"
        if cmd in ("nc_fail", "nc_fault", "nc_get", "nc_pos"):
            axis = plc.nc.axes[int(args[0])]
            axis.advance()
            if cmd == "nc_get":
                return ("ok", axis.describe())
            if cmd == "nc_fail":
                axis.fail_next = int(args[1], 0)
            elif cmd == "nc_pos":
                axis.pos = float(args[1])
            else:
                axis.fault(int(args[1], 0))
            return "ok"
        if cmd == "nc_channel":
            axes = [plc.nc.axes[int(a)] for a in args[1:]]
            if not 2 <= len(axes) <= 3:
                return ("error", "bad_arguments")
            plc.nc.channels[int(args[0])] = NciChannel(int(args[0]), axes)
            return "ok"
        if cmd in ("nc_channel_fail", "nc_channel_get"):
            channel = plc.nc.channels[int(args[0])]
            if cmd == "nc_channel_get":
                return ("ok", channel.describe())
            channel.fail_next = int(args[1], 0)
            return "ok"
        if cmd == "file_get":
            body = plc.nc.files.files.get(unquote(args[0]))
            return ("error", "no_file") if body is None else ("ok", body)
        if cmd == "quit":
            loop.stop()
            return "ok"
        return ("error", "unknown_command")
    except (IndexError, ValueError, KeyError, AttributeError) as e:
        return ("error", "bad_arguments")


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--port", type=int, default=0)
    parser.add_argument("--handle-base", type=int, default=0x1000)
    # Accept connections but answer nothing until `unmute': a PLC still starting up.
    parser.add_argument("--muted", action="store_true")
    # The cycle of the PLC task that serves notifications, in ms.
    parser.add_argument("--task-ms", type=float, default=10)
    args = parser.parse_args()
    plc = Plc(args.handle_base, args.task_ms / 1000)
    plc.muted = args.muted
    loop = asyncio.new_event_loop()
    asyncio.set_event_loop(loop)
    server = loop.run_until_complete(
        loop.create_server(lambda: Conn(plc), "127.0.0.1", args.port, reuse_address=True))
    port = server.sockets[0].getsockname()[1]

    def say(reply):
        sys.stdout.write(erl(reply) + "\n")
        sys.stdout.flush()

    def answer(line):
        reply = control(plc, line, loop, say)
        if reply is not None:
            say(reply)

    def reader():
        for line in sys.stdin:
            loop.call_soon_threadsafe(answer, line)
        # The test closed our stdin (or died): stop.
        loop.call_soon_threadsafe(loop.stop)

    threading.Thread(target=reader, daemon=True).start()
    sys.stdout.write(erl(("ready", port, os.getpid())) + "\n")
    sys.stdout.flush()
    loop.run_forever()


if __name__ == "__main__":
    main()
