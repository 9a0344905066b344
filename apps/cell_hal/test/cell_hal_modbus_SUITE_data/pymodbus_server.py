"""A Modbus TCP server on pymodbus, a test peer of cell_hal_modbus.

    python3 pymodbus_server.py [PORT]   listens on 127.0.0.1:PORT (0 or none: a free
                                        port) and prints "port N" once listening

It serves unit 1 only (requests to other units go unanswered, as pymodbus does) from
2000 coils, discrete inputs, holding and input registers; reading past them is
exception 2. Commands on stdin, one a line, each answered "ok ..." on stdout:

    set co|di|hr|ir ADDR V...   set values (bits 0/1, registers 0..65535)
    get co|di|hr|ir ADDR N      "ok V..."
    silent 1|0                  stop answering (requests time out) / answer again
"""
import asyncio
import logging
import sys
import threading

from pymodbus.datastore import (ModbusSequentialDataBlock, ModbusServerContext,
                                ModbusSlaveContext)
from pymodbus.server.async_io import ModbusConnectedRequestHandler, ModbusTcpServer

SIZE = 2000
logging.basicConfig(level=logging.CRITICAL)


SILENT = False


class Handler(ModbusConnectedRequestHandler):
    """Drops every request while the suite wants the server silent."""

    def execute(self, request, *addr):
        if not SILENT:
            super().execute(request, *addr)


def block():
    return ModbusSequentialDataBlock(0, [0] * SIZE)


def main():
    port = int(sys.argv[1]) if len(sys.argv) > 1 else 0
    slave = ModbusSlaveContext(co=block(), di=block(), hr=block(), ir=block(),
                               zero_mode=True)
    context = ModbusServerContext(slaves={1: slave}, single=False)
    loop = asyncio.new_event_loop()
    asyncio.set_event_loop(loop)
    # A request for a unit the context does not hold gets no answer at all.
    server = ModbusTcpServer(context, address=("127.0.0.1", port),
                             handler=Handler, allow_reuse_address=True,
                             ignore_missing_slaves=True, loop=loop)
    task = loop.create_task(server.serve_forever())
    loop.run_until_complete(server.serving)
    print("port", server.server.sockets[0].getsockname()[1], flush=True)

    tables = {"co": 1, "di": 2, "hr": 3, "ir": 4}

    def command(line):
        words = line.split()
        if not words:
            return None
        if words[0] == "set" and words[1] in tables:
            values = [int(v) for v in words[3:]]
            if words[1] in ("co", "di"):
                values = [bool(v) for v in values]
            slave.setValues(tables[words[1]], int(words[2]), values)
            return "ok"
        if words[0] == "get" and words[1] in tables:
            values = slave.getValues(tables[words[1]], int(words[2]), int(words[3]))
            return "ok " + " ".join(str(int(v)) for v in values)
        if words[0] == "silent":
            global SILENT
            SILENT = words[1] == "1"
            return "ok"
        return "error " + words[0]

    def stdin_reader():
        for line in sys.stdin:
            done = threading.Event()
            result = []

            def run(line=line):
                result.append(command(line))
                done.set()

            loop.call_soon_threadsafe(run)
            done.wait()
            if result[0] is not None:
                print(result[0], flush=True)
        # The suite closed stdin: stop.
        loop.call_soon_threadsafe(task.cancel)

    threading.Thread(target=stdin_reader, daemon=True).start()
    try:
        loop.run_until_complete(task)
    except asyncio.CancelledError:
        pass


if __name__ == "__main__":
    main()
