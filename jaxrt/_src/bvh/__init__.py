"""Linear BVH construction: Morton codes, the Karras radix tree, node boxes, quality metrics."""
