"""The simulated instrument's physics side: stages, lamp, sensor, colour, clock, seeded
systematic errors and faults, the sample and the holder scene.
"""
