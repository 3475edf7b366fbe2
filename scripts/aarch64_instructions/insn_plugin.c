/* A QEMU TCG plugin (plugin API version 1, QEMU 7.2 and later): counts the guest instructions a
 * program executes and prints "instructions N" to stderr at exit. With the argument blocks=PATH
 * it also writes, per translated block, "ADDRESS COUNT" (hexadecimal guest address, instructions
 * executed there) to PATH, for attributing them to the program's libraries. Declared here rather
 * than from qemu-plugin.h, which distributions do not package. */
#include <stddef.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

typedef uint64_t qemu_plugin_id_t;
typedef struct qemu_info_t qemu_info_t;
struct qemu_plugin_tb;
enum qemu_plugin_op { QEMU_PLUGIN_INLINE_ADD_U64 };
typedef void (*qemu_plugin_vcpu_tb_trans_cb_t)(qemu_plugin_id_t id, struct qemu_plugin_tb *tb);
typedef void (*qemu_plugin_udata_cb_t)(qemu_plugin_id_t id, void *userdata);
void qemu_plugin_register_vcpu_tb_trans_cb(qemu_plugin_id_t id, qemu_plugin_vcpu_tb_trans_cb_t cb);
size_t qemu_plugin_tb_n_insns(const struct qemu_plugin_tb *tb);
uint64_t qemu_plugin_tb_vaddr(const struct qemu_plugin_tb *tb);
void qemu_plugin_register_vcpu_tb_exec_inline(struct qemu_plugin_tb *tb, enum qemu_plugin_op op, void *ptr,
                                              uint64_t imm);
void qemu_plugin_register_atexit_cb(qemu_plugin_id_t id, qemu_plugin_udata_cb_t cb, void *userdata);

__attribute__((visibility("default"))) int qemu_plugin_version = 1;

static uint64_t executed;

/* Per-block counters live in chunks that never move: each translated block adds to its own. */
enum { CHUNK = 1 << 16 };
struct block { uint64_t vaddr, count; };
static struct block **chunks;
static size_t n_blocks, n_chunks;
static const char *blocks_path;

static uint64_t *new_block(uint64_t vaddr) {
    if (n_blocks == n_chunks * CHUNK) {
        struct block **grown = realloc(chunks, (n_chunks + 1) * sizeof *chunks);
        if (!grown || !(grown[n_chunks] = calloc(CHUNK, sizeof(struct block)))) {
            if (grown) chunks = grown;
            return NULL;
        }
        chunks = grown;
        n_chunks++;
    }
    struct block *b = &chunks[n_blocks / CHUNK][n_blocks % CHUNK];
    n_blocks++;
    b->vaddr = vaddr;
    return &b->count;
}

/* Each translated block adds its instruction count whenever it runs (the programs here are single-threaded). */
static void on_translate(qemu_plugin_id_t id, struct qemu_plugin_tb *tb) {
    (void)id;
    const size_t n = qemu_plugin_tb_n_insns(tb);
    qemu_plugin_register_vcpu_tb_exec_inline(tb, QEMU_PLUGIN_INLINE_ADD_U64, &executed, n);
    uint64_t *count = blocks_path ? new_block(qemu_plugin_tb_vaddr(tb)) : NULL;
    if (count) qemu_plugin_register_vcpu_tb_exec_inline(tb, QEMU_PLUGIN_INLINE_ADD_U64, count, n);
}

static void at_exit(qemu_plugin_id_t id, void *userdata) {
    (void)id, (void)userdata;
    fprintf(stderr, "instructions %llu\n", (unsigned long long)executed);
    FILE *out = blocks_path ? fopen(blocks_path, "w") : NULL;
    if (!out) return;
    for (size_t i = 0; i < n_blocks; i++) {
        const struct block *b = &chunks[i / CHUNK][i % CHUNK];
        if (b->count) fprintf(out, "%llx %llu\n", (unsigned long long)b->vaddr, (unsigned long long)b->count);
    }
    fclose(out);
}

__attribute__((visibility("default"))) int qemu_plugin_install(qemu_plugin_id_t id, const qemu_info_t *info,
                                                               int argc, char **argv) {
    (void)info;
    for (int i = 0; i < argc; i++)
        if (strncmp(argv[i], "blocks=", 7) == 0) blocks_path = strdup(argv[i] + 7);
    qemu_plugin_register_vcpu_tb_trans_cb(id, on_translate);
    qemu_plugin_register_atexit_cb(id, at_exit, NULL);
    return 0;
}
