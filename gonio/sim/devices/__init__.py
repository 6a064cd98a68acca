"""The simulated instrument's protocol side: the Zaber ASCII chain, the SCPI power meter,
the camera port and the byte-stream endpoint they share.
"""
