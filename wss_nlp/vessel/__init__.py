"""The vessel in a 4D flow volume: its lumen mask (:mod:`.segmentation`) and its centreline (:mod:`.centerline`)."""
