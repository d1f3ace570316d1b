"""Mesh queries on a triangle surface: BVH handle, ray casting, signed distance."""
