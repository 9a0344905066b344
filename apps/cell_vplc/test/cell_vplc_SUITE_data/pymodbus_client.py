"""A pymodbus client of the virtual PLC, a test peer of cell_vplc_SUITE.

    python3 pymodbus_client.py PORT

Reads robots' and the air's registers of the router's map (unit 1: the lower robot's
group at base 200, the upper robot's at 260, the general IO at 300) and prints one
line each:

    target V        holding register 260, the upper robot's position, a 16-bit integer
    command V       holding registers 261..262, a signed 32-bit integer
    spindle_run B   coil 200
    done V          input registers 260..261
    air_pressure V  input registers 300..303, a 64-bit float, high word first

then "end".
"""
import struct
import sys

from pymodbus.client import ModbusTcpClient


def words(regs, fmt):
    return struct.unpack(fmt, struct.pack(">%dH" % len(regs), *regs))[0]


def main():
    client = ModbusTcpClient("127.0.0.1", port=int(sys.argv[1]), timeout=10)
    if not client.connect():
        print("error cannot connect", flush=True)
        return 1
    target = client.read_holding_registers(260, 1, slave=1)
    print("target %d" % words(target.registers, ">h"), flush=True)
    command = client.read_holding_registers(261, 2, slave=1)
    print("command %d" % words(command.registers, ">i"), flush=True)
    spindle = client.read_coils(200, 1, slave=1)
    print("spindle_run %d" % int(spindle.bits[0]), flush=True)
    done = client.read_input_registers(260, 2, slave=1)
    print("done %d" % words(done.registers, ">i"), flush=True)
    air = client.read_input_registers(300, 4, slave=1)
    print("air_pressure %r" % words(air.registers, ">d"), flush=True)
    client.close()
    print("end", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
