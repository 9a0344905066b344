"""A PLC's I/O block held in a Modbus TCP server on pymodbus, a test peer of the
inspection block (cell_inspect).

    python3 plc_server.py [PORT]    listens on 127.0.0.1:PORT (0 or none: a free port)
                                    and prints "port N" once listening

It serves unit 1 from 2000 holding registers. The test plays the PLC through commands
on stdin, one a line, each answered "ok ..." on stdout:

    set ADDR V...     the PLC writes registers (0..65535)
    get ADDR N        "ok V..."
    silent 1|0        stop answering (requests time out) / answer again

Every write that comes over the network (function codes 6, 16, 22) is reported as it
is made, on stdout: "w ADDR V...", the registers' new values. All output comes from
the server's event loop, so lines never interleave.
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
FROM_TEST = False


def say(line):
    sys.stdout.write(line + "\n")
    sys.stdout.flush()


class Block(ModbusSequentialDataBlock):
    """Holding registers that report what the network writes."""

    def setValues(self, address, values):
        super().setValues(address, values)
        if not FROM_TEST:
            if not isinstance(values, list):
                values = [values]
            # zero_mode: the address is the protocol's, from 0.
            say("w %d %s" % (address, " ".join(str(int(v)) for v in values)))


class Handler(ModbusConnectedRequestHandler):
    """Drops every request while the test wants the PLC silent."""

    def execute(self, request, *addr):
        if not SILENT:
            super().execute(request, *addr)


def main():
    port = int(sys.argv[1]) if len(sys.argv) > 1 else 0
    hr = Block(0, [0] * SIZE)
    slave = ModbusSlaveContext(hr=hr, co=ModbusSequentialDataBlock(0, [0] * 10),
                               di=ModbusSequentialDataBlock(0, [0] * 10),
                               ir=ModbusSequentialDataBlock(0, [0] * 10), zero_mode=True)
    context = ModbusServerContext(slaves={1: slave}, single=False)
    loop = asyncio.new_event_loop()
    asyncio.set_event_loop(loop)
    server = ModbusTcpServer(context, address=("127.0.0.1", port), handler=Handler,
                             allow_reuse_address=True, ignore_missing_slaves=True, loop=loop)
    task = loop.create_task(server.serve_forever())
    loop.run_until_complete(server.serving)
    say("port %d" % server.server.sockets[0].getsockname()[1])

    def command(line):
        global SILENT, FROM_TEST
        words = line.split()
        if not words:
            return None
        if words[0] == "set":
            FROM_TEST = True
            try:
                slave.setValues(3, int(words[1]), [int(v) for v in words[2:]])
            finally:
                FROM_TEST = False
            return "ok"
        if words[0] == "get":
            values = slave.getValues(3, int(words[1]), int(words[2]))
            return "ok " + " ".join(str(int(v)) for v in values)
        if words[0] == "silent":
            SILENT = words[1] == "1"
            return "ok"
        return "error " + words[0]

    def stdin_reader():
        for line in sys.stdin:
            done = threading.Event()

            def run(line=line):
                result = command(line)
                if result is not None:
                    say(result)
                done.set()

            loop.call_soon_threadsafe(run)
            done.wait()
        loop.call_soon_threadsafe(task.cancel)

    threading.Thread(target=stdin_reader, daemon=True).start()
    try:
        loop.run_until_complete(task)
    except asyncio.CancelledError:
        pass


if __name__ == "__main__":
    main()
