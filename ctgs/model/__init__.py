"""The textured surfel model: raw (pre-activation) parameters + jagged textures."""
