"""Where the instrument goes: measurement plans, the rig's kinematics, move ordering and
the holder's markers.
"""
