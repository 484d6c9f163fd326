/* LPC2148 start-up: exception vectors (IRQ through the VIC's vector address register),
 * stacks, .data copied from flash, .bss cleared, then main(). ARM mode, ARM7TDMI-S. */
        .section .vectors, "ax"
        .arm
        .global _start
_start:
        ldr     pc, reset_addr
        ldr     pc, undef_addr
        ldr     pc, swi_addr
        ldr     pc, pabt_addr
        ldr     pc, dabt_addr
        .word   0                       /* vector checksum: make arm writes it in the .bin */
        ldr     pc, [pc, #-0xFF0]       /* IRQ: jump to VICVectAddr */
        ldr     pc, fiq_addr
reset_addr:     .word reset_handler
undef_addr:     .word hang
swi_addr:       .word hang
pabt_addr:      .word hang
dabt_addr:      .word hang
fiq_addr:       .word hang

        .text
        .arm
reset_handler:
        msr     cpsr_c, #0xD2           /* IRQ mode, interrupts off */
        ldr     sp, =_irq_stack_top
        msr     cpsr_c, #0xD3           /* supervisor mode, interrupts off */
        ldr     sp, =_stack_top
        ldr     r0, =_sidata            /* copy .data */
        ldr     r1, =_sdata
        ldr     r2, =_edata
1:      cmp     r1, r2
        ldrlo   r3, [r0], #4
        strlo   r3, [r1], #4
        blo     1b
        ldr     r1, =_sbss              /* clear .bss */
        ldr     r2, =_ebss
        mov     r3, #0
2:      cmp     r1, r2
        strlo   r3, [r1], #4
        blo     2b
        bl      main
        /* an undefined instruction, an abort, SWI or FIQ (or main's return): both valves
         * closed, then wait for the watchdog's reset (a loop alone left an open valve open
         * for the watchdog's 10 s: a review's finding). The valves are Timer1's match
         * outputs (board.c, valves.h): their bits cleared in T1EMR, then P0.12 / P0.13 made
         * GPIO again, driven low by IO0CLR (board.c set them as low outputs). */
hang:   ldr     r0, =0xE000803C         /* T1EMR: EM0 = EM1 = 0 */
        mov     r1, #0
        str     r1, [r0]
        ldr     r0, =0xE002800C         /* IO0CLR: P0.12, P0.13 */
        mov     r1, #0x3000
        str     r1, [r0]
        ldr     r0, =0xE002C000         /* PINSEL0: P0.12, P0.13 GPIO */
        ldr     r1, [r0]
        bic     r1, r1, #0x0F000000
        str     r1, [r0]
3:      b       3b
