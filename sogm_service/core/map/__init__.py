"""The tiled map: tiles and their planes, the lattice's types, footprints priced from headers,
layers that forget, coarse gathering and the tile manager.
"""
