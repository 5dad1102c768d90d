/*
 * vlff_scene_box: a scene's box file (bbox.txt) read into
 * field.scene_min/max.
 *
 * Format: six numbers, min x y z then max x y z in metres, separated by
 * white space or commas (the reference layout's bbox.txt, read as the scene
 * reader reads it: docs/datasets.md).
 *
 * Contract
 *  - 0, or -1 with one line in err naming the file and what is wrong.
 *  - Only a regular file of at most 4 KiB is read (files.h); every number
 *    must be finite, within +-1e4 m (the bounds of field.scene_min/max),
 *    min < max on every axis, and nothing but white space may follow.
 */
#ifndef VLFF_SCENE_BOX_H
#define VLFF_SCENE_BOX_H

#include <stddef.h>

int vlff_scene_box_read(const char *path, double lo[3], double hi[3], char *err, size_t errlen);
int vlff_scene_box_parse(const char *text, const char *name, double lo[3], double hi[3], char *err, size_t errlen);

#endif
