//! Plots (written by the plotting work in progress).
