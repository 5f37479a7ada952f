/*
 * icount: a QEMU TCG plugin that counts the guest instructions executed
 * between marker functions, for scripts/qemu-bench.
 *
 *   -plugin libicount.so,start=0xADDR,stop=0xADDR,report=0xADDR
 *
 * Every executed guest instruction adds 1 to a counter (inline TCG op, no
 * helper call). When the instruction at `start` executes, the counter is
 * snapshotted; at `stop`, the difference is one call's count (min, max and
 * sum are accumulated); at `report`, the plugin prints
 *   ICOUNT <calls> <min> <max> <sum>
 * to QEMU's log (stderr) and resets. Conditionally skipped instructions (IT
 * blocks) count as executed, as on the Cortex-M7 they take an issue slot.
 *
 * Optional `profile=FILE` (scripts/qemu-bench --profile): also counts, per
 * guest instruction address, the executions inside measured calls, and at
 * each `report` appends to FILE a line `REPORT <n>` followed by
 * `<address hex> <count>` lines (addresses with a non-zero count), then
 * resets. Slower (one helper call per instruction); the totals are the same.
 *
 * Optional `trace=FILE` (scripts/qemu-cycles): writes the address of every
 * instruction executed in the *first* measured call after each report (the
 * first call of each benchmark), in execution order, one hex address a line,
 * each call after a line `CALL <report index>`. The executed instruction
 * stream for a pipeline model (llvm-mca).
 *
 * Debian does not ship qemu-plugin.h (QEMU's public plugin header), so the
 * few declarations used are below; they are those of the plugin API version 1
 * (QEMU 6.0 .. 8.1; QEMU 7.2 in Debian 12). The API is a C ABI of functions
 * exported by the qemu-system-* binary.
 */
#include <inttypes.h>
#include <stdbool.h>
#include <stddef.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#define QEMU_PLUGIN_EXPORT __attribute__((visibility("default")))

typedef uint64_t qemu_plugin_id_t;
typedef struct qemu_info_t qemu_info_t; /* only passed through */
struct qemu_plugin_tb;
struct qemu_plugin_insn;

enum qemu_plugin_cb_flags {
    QEMU_PLUGIN_CB_NO_REGS,
    QEMU_PLUGIN_CB_R_REGS,
    QEMU_PLUGIN_CB_RW_REGS,
};

enum qemu_plugin_op {
    QEMU_PLUGIN_INLINE_ADD_U64,
};

typedef void (*qemu_plugin_vcpu_tb_trans_cb_t)(qemu_plugin_id_t id,
                                               struct qemu_plugin_tb *tb);
typedef void (*qemu_plugin_vcpu_udata_cb_t)(unsigned int vcpu_index,
                                            void *userdata);
typedef void (*qemu_plugin_udata_cb_t)(qemu_plugin_id_t id, void *userdata);

void qemu_plugin_register_vcpu_tb_trans_cb(qemu_plugin_id_t id,
                                           qemu_plugin_vcpu_tb_trans_cb_t cb);
size_t qemu_plugin_tb_n_insns(const struct qemu_plugin_tb *tb);
struct qemu_plugin_insn *qemu_plugin_tb_get_insn(const struct qemu_plugin_tb *tb,
                                                 size_t idx);
uint64_t qemu_plugin_insn_vaddr(const struct qemu_plugin_insn *insn);
void qemu_plugin_register_vcpu_insn_exec_cb(struct qemu_plugin_insn *insn,
                                            qemu_plugin_vcpu_udata_cb_t cb,
                                            enum qemu_plugin_cb_flags flags,
                                            void *userdata);
void qemu_plugin_register_vcpu_insn_exec_inline(struct qemu_plugin_insn *insn,
                                                enum qemu_plugin_op op,
                                                void *ptr, uint64_t imm);
void qemu_plugin_register_atexit_cb(qemu_plugin_id_t id,
                                    qemu_plugin_udata_cb_t cb, void *userdata);
void qemu_plugin_outs(const char *string);

QEMU_PLUGIN_EXPORT int qemu_plugin_version = 1;

enum marker { START, STOP, REPORT };

static uint64_t addr[3] = {UINT64_MAX, UINT64_MAX, UINT64_MAX};
static uint64_t executed; /* the guest is single-core: one counter */
static uint64_t at_start;
static bool in_call;
static uint64_t calls, sum, min_n, max_n;
static uint64_t total_reports;

/* Profile: executions per instruction address (halfword index) in calls. */
#define PROF_SLOTS (1u << 20) /* 2 MiB of code */
static uint64_t *prof;
static FILE *prof_file;

/* Trace: the first call of each benchmark, instruction by instruction. */
static FILE *trace_file;
static bool tracing;

static void on_insn(unsigned int vcpu, void *udata)
{
    (void)vcpu;
    if (in_call) {
        if (prof) {
            prof[(uintptr_t)udata]++;
        }
        if (tracing) {
            fprintf(trace_file, "%zx\n", (size_t)(uintptr_t)udata * 2);
        }
    }
}

static void prof_dump(void)
{
    fprintf(prof_file, "REPORT %" PRIu64 "\n", total_reports);
    for (size_t i = 0; i < PROF_SLOTS; i++) {
        if (prof[i]) {
            fprintf(prof_file, "%zx %" PRIu64 "\n", i * 2, prof[i]);
            prof[i] = 0;
        }
    }
    fflush(prof_file);
}

static void on_marker(unsigned int vcpu, void *udata)
{
    char line[128];
    (void)vcpu;
    switch ((enum marker)(uintptr_t)udata) {
    case START:
        at_start = executed;
        in_call = true;
        if (trace_file && calls == 0) {
            tracing = true;
            fprintf(trace_file, "CALL %" PRIu64 "\n", total_reports);
        }
        break;
    case STOP:
        if (in_call) {
            uint64_t n = executed - at_start;
            if (calls == 0 || n < min_n) {
                min_n = n;
            }
            if (calls == 0 || n > max_n) {
                max_n = n;
            }
            sum += n;
            calls++;
            in_call = false;
            tracing = false;
        }
        break;
    case REPORT:
        snprintf(line, sizeof line, "ICOUNT %" PRIu64 " %" PRIu64 " %" PRIu64
                 " %" PRIu64 "\n", calls, min_n, max_n, sum);
        qemu_plugin_outs(line);
        if (prof_file) {
            prof_dump();
        }
        calls = sum = min_n = max_n = 0;
        in_call = false;
        tracing = false;
        total_reports++;
        break;
    }
}

static void tb_trans(qemu_plugin_id_t id, struct qemu_plugin_tb *tb)
{
    size_t n = qemu_plugin_tb_n_insns(tb);
    (void)id;
    for (size_t i = 0; i < n; i++) {
        struct qemu_plugin_insn *insn = qemu_plugin_tb_get_insn(tb, i);
        uint64_t va = qemu_plugin_insn_vaddr(insn);
        for (int m = START; m <= REPORT; m++) {
            if (va == addr[m]) {
                qemu_plugin_register_vcpu_insn_exec_cb(
                    insn, on_marker, QEMU_PLUGIN_CB_NO_REGS,
                    (void *)(uintptr_t)m);
            }
        }
        qemu_plugin_register_vcpu_insn_exec_inline(
            insn, QEMU_PLUGIN_INLINE_ADD_U64, &executed, 1);
        if ((prof_file || trace_file) && va / 2 < PROF_SLOTS) {
            qemu_plugin_register_vcpu_insn_exec_cb(
                insn, on_insn, QEMU_PLUGIN_CB_NO_REGS, (void *)(uintptr_t)(va / 2));
        }
    }
}

static void at_exit(qemu_plugin_id_t id, void *p)
{
    char line[96];
    (void)id;
    (void)p;
    if (trace_file) {
        fclose(trace_file);
        trace_file = NULL;
    }
    snprintf(line, sizeof line, "ICOUNT_TOTAL %" PRIu64 " %" PRIu64 "\n",
             executed, total_reports);
    qemu_plugin_outs(line);
}

QEMU_PLUGIN_EXPORT int qemu_plugin_install(qemu_plugin_id_t id,
                                           const qemu_info_t *info, int argc,
                                           char **argv)
{
    static const char *const names[3] = {"start=", "stop=", "report="};
    (void)info;
    for (int i = 0; i < argc; i++) {
        bool known = false;
        if (strncmp(argv[i], "profile=", 8) == 0) {
            prof_file = fopen(argv[i] + 8, "w");
            prof = calloc(PROF_SLOTS, sizeof *prof);
            if (!prof_file || !prof) {
                fprintf(stderr, "icount: cannot open profile '%s'\n", argv[i] + 8);
                return -1;
            }
            continue;
        }
        if (strncmp(argv[i], "trace=", 6) == 0) {
            trace_file = fopen(argv[i] + 6, "w");
            if (!trace_file) {
                fprintf(stderr, "icount: cannot open trace '%s'\n", argv[i] + 6);
                return -1;
            }
            continue;
        }
        for (int m = START; m <= REPORT; m++) {
            size_t len = strlen(names[m]);
            if (strncmp(argv[i], names[m], len) == 0) {
                /* Thumb symbols have bit 0 set; instructions are at even addresses. */
                addr[m] = strtoull(argv[i] + len, NULL, 0) & ~(uint64_t)1;
                known = true;
            }
        }
        if (!known) {
            fprintf(stderr, "icount: unknown argument '%s'\n", argv[i]);
            return -1;
        }
    }
    for (int m = START; m <= REPORT; m++) {
        if (addr[m] == UINT64_MAX) {
            fprintf(stderr, "icount: missing %s<address>\n", names[m]);
            return -1;
        }
    }
    qemu_plugin_register_vcpu_tb_trans_cb(id, tb_trans);
    qemu_plugin_register_atexit_cb(id, at_exit, NULL);
    return 0;
}
