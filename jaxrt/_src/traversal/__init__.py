"""BVH traversal: the portable stack traversal (one ray, vmapped) and GPU kernels behind the same contract.

Contract of every traversal: for each ray it returns the distance of the accepted hit (``inf`` on a miss) and
the leaf that holds it (``-1`` on a miss). The intersector then recomputes the hit on that leaf for the
result fields, so a traversal only has to pick the primitive.
"""
