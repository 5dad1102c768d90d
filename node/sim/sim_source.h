/*
 * The simulator as the node's scene source (node/core/source.h): what
 * vlff-sim's scene gives a node reading its frames.
 *
 *  - source.features: sim: each frame's features, rendered for the ring's
 *    frame id modulo sim.frames (vlff-sim loops its trajectory), and the
 *    simulated text encoder for the prompts;
 *  - source.kind: sim: the ground truth: every published map is scored
 *    (2D at the label image's frame, 3D on the scene's labelled surface
 *    points), and snapshots show the scene's image and truth.
 *
 * Contract: create fills hooks (members the config asks for; the others
 * NULL) and keeps the simulator; destroy after the node that used them.
 * The hooks follow source.h's threading: one features caller, one caller of
 * the rest, each with its own render buffer.
 */
#ifndef VLFF_SIM_SOURCE_H
#define VLFF_SIM_SOURCE_H

#include <stddef.h>

#include "config.h"
#include "source.h"

struct vlff_sim_source;

/* NULL with err filled on failure; a config that asks for nothing of the
 * simulator gives a source whose hooks are all NULL. */
struct vlff_sim_source *vlff_sim_source_create(const struct vlff_config *cfg, struct vlff_source_hooks *hooks,
                                               char *err, size_t errlen);
void vlff_sim_source_destroy(struct vlff_sim_source *s);

#endif
