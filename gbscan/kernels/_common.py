"""Colour classes of the decoder's label images, shared by the kernel modules."""
NONE, GREEN, BLUE, CYAN = 0, 1, 2, 3
