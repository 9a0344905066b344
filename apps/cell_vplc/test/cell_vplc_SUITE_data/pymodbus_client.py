"""A pymodbus client of the virtual PLC, a test peer of cell_vplc_SUITE.

    python3 pymodbus_client.py PORT

Reads the lower routing robot's registers of the router's map (unit 1, the lower
robot's group at base 200) and prints one line each:

    target_x V      holding registers 200..203, a 64-bit float, high word first
    command V       holding registers 216..217, a signed 32-bit integer
    spindle_run B   coil 200
    done V          input registers 200..201

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
    target = client.read_holding_registers(200, 4, slave=1)
    print("target_x %r" % words(target.registers, ">d"), flush=True)
    command = client.read_holding_registers(216, 2, slave=1)
    print("command %d" % words(command.registers, ">i"), flush=True)
    spindle = client.read_coils(200, 1, slave=1)
    print("spindle_run %d" % int(spindle.bits[0]), flush=True)
    done = client.read_input_registers(200, 2, slave=1)
    print("done %d" % words(done.registers, ">i"), flush=True)
    client.close()
    print("end", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
