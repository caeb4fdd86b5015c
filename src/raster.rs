//! Rasterizer (placeholder).
