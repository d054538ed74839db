"""Decoders that turn wrapped frames into winding numbers; see :mod:`models.decoders.registry`."""

from models.decoders.base import Decoder, DecodeResult
from models.decoders.registry import DecoderSpec, available_decoders, get_decoder

__all__ = ["DecodeResult", "Decoder", "DecoderSpec", "available_decoders", "get_decoder"]
