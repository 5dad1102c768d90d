/*
 * vlff-shm dump-map: a map segment's current version to a file.
 *
 * The version is copied with vlff_map_snapshot_take (consistent, never
 * waits for the writer) and written atomically (temp file, rename); a FILE
 * that exists and is not a regular file (a device, a FIFO, a directory) is
 * refused, never replaced:
 *  - FILE ending in ".ply": binary little-endian PLY, one vertex per voxel
 *    holding a prompt's label (free and unknown voxels left out): float x y z
 *    (the voxel's centre, metres), uchar red green blue (vlff_label_color),
 *    ushort label, uchar confidence; "comment prompt K TEXT" header lines
 *    name the labels.
 *  - any other FILE: the vlff-map binary format, all little-endian:
 *      char magic[8] "VLFFMAP1"; uint64 version; uint64 publish_ns;
 *      double origin[3]; double voxel_size; uint32 dims[3];
 *      uint32 prompt_count; prompt_count x char[64] (NUL-padded);
 *      uint16 labels[dims2][dims1][dims0]; uint8 confidence[same]
 *    (labels as the segment holds them: 0xFFFE free, 0xFFFF unknown).
 * Prints "version V voxels N labelled L free F unknown U -> FILE".
 * Returns the program's exit status: 0, or 1 with the reason on stderr.
 */
#ifndef VLFF_SHM_DUMP_MAP_H
#define VLFF_SHM_DUMP_MAP_H

int vlff_dump_map(const char *name, const char *path);

/* vlff-shm's error line for a failed library call about what (a segment):
 * "vlff-shm: <the library's message>", what added when the message does not
 * name it. Returns 1, the exit status. */
int vlff_shm_fail(const char *what);

#endif
