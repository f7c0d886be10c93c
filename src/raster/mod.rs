//! The multithreaded CPU Gaussian rasterizer (forward and analytic backward), gsplat semantics.
