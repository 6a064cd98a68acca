import serial

if "benchfakes" not in serial.protocol_handler_packages:
    serial.protocol_handler_packages.append("benchfakes")
