/*
 * Regions of a label image: its surface cells grouped by colour and
 * geometry, and each cell's label voted with its region.
 *
 * Why: a vision-language model is wrong by whole surfaces, not by pixels.
 * Every view of a floor seen far and at a grazing angle leans toward a
 * look-alike class, and so does the map learned from those views; the
 * label image of a new view then reads a patch of floor as a desk where its
 * evidence leans over the margin, beside floor that reads floor. The
 * camera's own image says that patch and the floor around it are one
 * surface (same colour, no depth step between them), so the cell reads
 * what that surface reads as a whole (docs/field.md, "Regions").
 *
 * Cells: a lw x lh grid over a width x height camera image; the surface
 * cells are those with a measured surface point (select.h,
 * vlff_label_surface: pix[i] the cell, xyz[3 i] its world point). Two
 * neighbouring surface cells (8-neighbourhood) are joined by an edge of
 * weight
 *   2 |rgb_a - rgb_b| + max(0, |p_a - p_b| - 3 sigma) / 1 m
 * (rgb: the mean colour of the cell's image pixels in 0..1, Euclidean; p:
 * the measured points; sigma: the depth noise at the farther one's range
 * d from the camera, noise_1m d^2 as train.depth_noise_m says, so that a
 * stereo camera's noise does not cut a wall into pieces where a structured
 * light sensor's would not), and the edges are merged in increasing weight
 * into regions by Felzenszwalb and Huttenlocher's rule (IJCV 2004): two
 * regions join when the edge is no heavier than either region's largest
 * internal edge plus k / size, with k = 1 for every 2400 cells (the same
 * share of the image makes a region at any label image size), and when
 * their mean colours are at most 0.1 apart: the rule looks at edges
 * alone, and a chain of small steps would leak one surface into the next
 * (a checkered door into its wall through squares like the wall's).
 * Without colours (col NULL) colour does not separate anything; depth
 * steps still do.
 *
 * Vote: cell i's scores s_i[K] (the combined field and evidence sums of
 * evidence.h) plus beta times its region's mean scores, each cell weighing
 * in that mean its margin (best minus second sum) plus 0.02: a clear
 * reading says more about its surface than one that barely leans; its label
 * is the best of those, its score its own s_i at that label.
 *
 * Contract: a vlff_regions is scratch for one lw x lh grid, used by one
 * thread at a time; build, then vote with scores of the same cells in the
 * same order. Nothing is kept between builds.
 */
#ifndef VLFF_REGIONS_H
#define VLFF_REGIONS_H

#include <stddef.h>
#include <stdint.h>

struct vlff_regions;

/* Scratch for a lw x lh cell grid (NULL when out of memory or a size is
 * not positive). */
struct vlff_regions *vlff_regions_create(int lw, int lh);
void vlff_regions_destroy(struct vlff_regions *r);

/* The mean colour (0..1) of the image pixels under each of the n cells
 * pix[i] of a lw x lh grid over rgb (width x height x 3, row major) into
 * col[3 i]; 0 without an image or for a cell outside the grid. */
void vlff_regions_colours(const uint8_t *rgb, int width, int height, int lw, int lh, const uint32_t *pix, size_t n,
                          float *col);

/* Groups the n surface cells pix[0..n) (indices into the lw x lh grid; a
 * cell outside it or given twice is a region of its own; a point not
 * finite joins nothing; at most lw x lh cells: those past that are not
 * grouped) with measured world points xyz[3 n], colours col[3 n]
 * (vlff_regions_colours; NULL: no colour), the camera's position origin
 * and the depth noise's sigma at 1 m noise_1m (0, not a finite
 * non-negative number, or an origin that is not finite: every step
 * counts). Returns the number of regions. */
size_t vlff_regions_build(struct vlff_regions *r, const float *col, const uint32_t *pix, const float *xyz, size_t n,
                          const double origin[3], float noise_1m);

/* The region of surface cell i of the last build (0 .. regions - 1;
 * UINT32_MAX for a cell it did not group). */
uint32_t vlff_regions_of(const struct vlff_regions *r, size_t i);

/* Labels of the last build's n cells from their scores [n][K] (K >= 1),
 * voted with their regions at weight beta (> 0, however large; 0,
 * negative or not a number: each cell's own best): label[i], and score[i]
 * (may be NULL) cell i's own score at that label. A cell whose label is -1
 * on entry (nothing scored it), or with a score that is not finite (or
 * whose best two are too far apart for their margin to be), keeps its
 * label and adds nothing to its region; a cell whose region's weighted
 * sums overflow takes its own best; cells past the build's are left as
 * they are. 0, or -1 when out of memory (label untouched). */
int vlff_regions_vote(struct vlff_regions *r, const float *scores, size_t n, int K, float beta, int *label,
                      float *score);

#endif
