"""A pymodbus client of the virtual PLC, a test peer of cell_vplc_SUITE.

    python3 pymodbus_client.py PORT

Reads robots' and the air's registers of the router's map (unit 1: the lower robot's
group at base 200, the upper robot's at 260, the general IO at 300) and prints one
line each:

    x_actual V              holding registers 260..261, the upper robot's X axis
                            position from its NC, a 32-bit float, high word first
    y_actual V              holding registers 262..263, its Y axis, the same
    spindle_run B           coil 200
    at_unloading_front B    discrete input 265, the upper robot in position over the
                            front unloading segment
    air_pressure V          input registers 300..303, a 64-bit float, high word first

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
    x = client.read_holding_registers(260, 2, slave=1)
    print("x_actual %r" % words(x.registers, ">f"), flush=True)
    y = client.read_holding_registers(262, 2, slave=1)
    print("y_actual %r" % words(y.registers, ">f"), flush=True)
    spindle = client.read_coils(200, 1, slave=1)
    print("spindle_run %d" % int(spindle.bits[0]), flush=True)
    at = client.read_discrete_inputs(265, 1, slave=1)
    print("at_unloading_front %d" % int(at.bits[0]), flush=True)
    air = client.read_input_registers(300, 4, slave=1)
    print("air_pressure %r" % words(air.registers, ">d"), flush=True)
    client.close()
    print("end", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
