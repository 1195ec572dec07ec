// Every compute shader of the GL backend starts with this (after the #version and the
// #defines the backend generates from the numpy modules' constants: LOCAL, SLOTS, W0 ...).
layout(local_size_x = LOCAL) in;
uniform uint base;  // first item of this dispatch (large inputs are dispatched in chunks)
