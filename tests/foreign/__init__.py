"""Sequences written the way users write them (pypulseq scripts of our own, not dtoc's builder): no
FOV/matrix definitions, no system limits, the writers' default RF ``use`` (undefined)."""
