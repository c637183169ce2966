//! Dense RGB-D pose tracking (to be written).
