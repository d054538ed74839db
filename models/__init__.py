"""The camera's physics (image formation), file formats, metrics and decoders."""
