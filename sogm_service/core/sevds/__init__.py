"""SEVDS supercells (paper section III-D.2, Eq. 7-11): parameters and the public function, the
numba kernels apart, the supercell graph.
"""
