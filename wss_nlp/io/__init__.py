"""Files in and out: the HDF5 contract's layouts, scanner exports, and exports for other tools."""
