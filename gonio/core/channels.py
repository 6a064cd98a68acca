"""The channels a measurement carries, declared once: every layer reads them from here.

Today three colour channels (linear camera RGB, or the colour space a dataset is converted
to). A spectral measurement changes this declaration (a list of wavelengths), not the layers
that read it (docs/architecture.md, "What each coming capability touches").
"""

__all__ = ["CHANNELS", "COLOUR_SPACE_CHANNELS"]

#: Number of channels of every f_r value, parameter and uncertainty (linear camera RGB).
CHANNELS = 3

#: The channel names of each colour space a dataset may be fitted in.
COLOUR_SPACE_CHANNELS = {"srgb": ("R", "G", "B"), "xyz": ("X", "Y", "Z"), "camera": ("R", "G", "B")}
