"""Image I/O (OpenEXR, Radiance HDR, PNG/TIFF/JPEG), tone mapping, contact sheets. Writes are atomic.

The bottom layer of the package: it imports nothing else of hiddenjax.
"""

from ._exr import read_exr as read_exr
from ._exr import write_exr as write_exr
from ._images import HDR_SUFFIXES as HDR_SUFFIXES
from ._images import LDR_SUFFIXES as LDR_SUFFIXES
from ._images import colormap as colormap
from ._images import read_hdr as read_hdr
from ._images import read_image as read_image
from ._images import read_stored as read_stored
from ._images import srgb_to_linear as srgb_to_linear
from ._images import tonemap as tonemap
from ._images import write_hdr as write_hdr
from ._images import write_image as write_image
from ._images import write_png as write_png
from ._sheet import contact_sheet as contact_sheet
from ._sheet import panel as panel
from ._sheet import write_map as write_map
from ._sheet import write_plot as write_plot
from ._files import atomic_path as atomic_path
from ._files import read_toml as read_toml
from ._files import write_text as write_text
