#!/usr/bin/env python3
"""PyPI pyads' own ADS test server (AdsTestServer with its AdvancedHandler), as a peer
for the basic commands, on 127.0.0.1 and a port the OS picks.

Its limits shape the tests that use it: it reads one request per recv() (so a client
must keep one request in flight), sends no notifications over the wire, knows no sum
commands on handles, and drops the connection on an unknown symbol.

The symbol version (index group 0xF008), which every TwinCAT PLC serves, is added as a
variable so that a client can read and watch it.

Commands on stdin, one Erlang term a line on stdout:

    add NAME ADST TYPENAME HEX   -> {ok, Group, Offset}
    get NAME                     -> {ok, <<...>>}
    history                      -> {ok, [{Command, IndexGroup}]}   (every request so far;
                                    IndexGroup 0 for commands without one)
    quit
"""

import os
import sys

from pyads.testserver import AdsTestServer, AdvancedHandler, PLCVariable


def erl(term):
    if isinstance(term, int):
        return str(term)
    if isinstance(term, str):
        return term
    if isinstance(term, (bytes, bytearray)):
        return "<<" + ",".join(str(b) for b in term) + ">>"
    if isinstance(term, tuple):
        return "{" + ",".join(erl(t) for t in term) + "}"
    if isinstance(term, list):
        return "[" + ",".join(erl(t) for t in term) + "]"
    raise TypeError(term)


def history_entry(packet):
    header = packet.ams_header
    command = int.from_bytes(header.command_id, "little")
    group = int.from_bytes(header.data[:4], "little") if len(header.data) >= 4 else 0
    return (command, group)


def main():
    handler = AdvancedHandler()
    server = AdsTestServer(handler=handler, ip_address="127.0.0.1", port=0, logging=False)
    port = server.server.getsockname()[1]
    handler.add_variable(PLCVariable("SymbolVersion", b"\x01", 17, "BYTE",
                                     index_group=0xF008, index_offset=0))
    server.start()
    print(erl(("ready", port, os.getpid())), flush=True)
    for line in sys.stdin:
        words = line.split()
        if not words:
            continue
        cmd, args = words[0], words[1:]
        if cmd == "quit":
            break
        try:
            if cmd == "add":
                var = PLCVariable(args[0], bytes.fromhex(args[3]), int(args[1]), args[2])
                handler.add_variable(var)
                reply = ("ok", var.index_group, var.index_offset)
            elif cmd == "get":
                reply = ("ok", handler.get_variable_by_name(args[0]).value)
            elif cmd == "history":
                reply = ("ok", [history_entry(p) for p in server.request_history])
            else:
                reply = ("error", "unknown_command")
        except (IndexError, ValueError, KeyError):
            reply = ("error", "bad_arguments")
        print(erl(reply), flush=True)
    server.close()


if __name__ == "__main__":
    main()
