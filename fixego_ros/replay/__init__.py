"""Offline replay of image-level bags: tracking + flow + estimation in one process, no DDS."""
