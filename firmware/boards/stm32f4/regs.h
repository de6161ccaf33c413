/* The few STM32F405/407 and Cortex-M4 registers the boards use, from the reference manual RM0090 and the
 * Cortex-M4 generic user guide (addresses and bit positions only; no vendor header is needed). */
#ifndef FW_REGS_H
#define FW_REGS_H

#include <stdint.h>

#define REG(addr) (*(volatile uint32_t *)(addr))

/* ---- Cortex-M4 core ---- */
#define NVIC_ISER(n) REG(0xE000E100u + 4u * (n))
#define NVIC_IPR(n) (*(volatile uint8_t *)(0xE000E400u + (n)))   /* one byte per IRQ, top 4 bits used */

static inline void nvic_enable(unsigned irq, unsigned prio)
{
    NVIC_IPR(irq) = (uint8_t)(prio << 4);
    NVIC_ISER(irq / 32u) = 1u << (irq % 32u);
}

#define IRQ_EXTI1 7u

/* ---- RCC (RM0090 §7.3) ---- */
#define RCC_BASE 0x40023800u
#define RCC_CR REG(RCC_BASE + 0x00u)
#define RCC_PLLCFGR REG(RCC_BASE + 0x04u)
#define RCC_CFGR REG(RCC_BASE + 0x08u)
#define RCC_AHB1ENR REG(RCC_BASE + 0x30u)
#define RCC_APB1ENR REG(RCC_BASE + 0x40u)
#define RCC_APB2ENR REG(RCC_BASE + 0x44u)
#define RCC_CR_HSEON (1u << 16)
#define RCC_CR_HSERDY (1u << 17)
#define RCC_CR_PLLON (1u << 24)
#define RCC_CR_PLLRDY (1u << 25)
#define RCC_AHB1ENR_GPIOA (1u << 0)
#define RCC_AHB1ENR_GPIOB (1u << 1)
#define RCC_APB1ENR_TIM2 (1u << 0)
#define RCC_APB2ENR_USART1 (1u << 4)
#define RCC_APB2ENR_ADC1 (1u << 8)
#define RCC_APB2ENR_SPI1 (1u << 12)
#define RCC_APB2ENR_SYSCFG (1u << 14)

/* ---- FLASH interface ---- */
#define FLASH_ACR REG(0x40023C00u)

/* ---- GPIO (RM0090 §8.4) ---- */
#define GPIOA_BASE 0x40020000u
#define GPIOB_BASE 0x40020400u
#define GPIO_MODER(p) REG((p) + 0x00u)
#define GPIO_OSPEEDR(p) REG((p) + 0x08u)
#define GPIO_PUPDR(p) REG((p) + 0x0Cu)
#define GPIO_IDR(p) REG((p) + 0x10u)
#define GPIO_BSRR(p) REG((p) + 0x18u)
#define GPIO_AFR(p, n) REG((p) + 0x20u + 4u * (n))

/* ---- USART (RM0090 §30.6) ---- */
#define USART1_BASE 0x40011000u
#define USART_SR(u) REG((u) + 0x00u)
#define USART_DR(u) REG((u) + 0x04u)
#define USART_BRR(u) REG((u) + 0x08u)
#define USART_CR1(u) REG((u) + 0x0Cu)
#define USART_SR_TC (1u << 6)
#define USART_SR_TXE (1u << 7)
#define USART_CR1_TE (1u << 3)
#define USART_CR1_UE (1u << 13)

/* ---- SPI1 (RM0090 §28.5) ---- */
#define SPI1_BASE 0x40013000u
#define SPI_CR1(s) REG((s) + 0x00u)
#define SPI_SR(s) REG((s) + 0x08u)
#define SPI_DR(s) REG((s) + 0x0Cu)
#define SPI_CR1_CPHA (1u << 0)
#define SPI_CR1_MSTR (1u << 2)
#define SPI_CR1_BR_DIV8 (2u << 3)
#define SPI_CR1_SPE (1u << 6)
#define SPI_CR1_SSI (1u << 8)
#define SPI_CR1_SSM (1u << 9)
#define SPI_SR_RXNE (1u << 0)
#define SPI_SR_TXE (1u << 1)
#define SPI_SR_BSY (1u << 7)

/* ---- TIM2, 32-bit general-purpose timer (RM0090 §18.4) ---- */
#define TIM2_BASE 0x40000000u
#define TIM2_CR1 REG(TIM2_BASE + 0x00u)
#define TIM2_SR REG(TIM2_BASE + 0x10u)
#define TIM2_EGR REG(TIM2_BASE + 0x14u)
#define TIM2_CCMR1 REG(TIM2_BASE + 0x18u)
#define TIM2_CCER REG(TIM2_BASE + 0x20u)
#define TIM2_CNT REG(TIM2_BASE + 0x24u)
#define TIM2_PSC REG(TIM2_BASE + 0x28u)
#define TIM2_ARR REG(TIM2_BASE + 0x2Cu)
#define TIM2_CCR1 REG(TIM2_BASE + 0x34u)
#define TIM2_CCR2 REG(TIM2_BASE + 0x38u)
#define TIM_SR_CC1IF (1u << 1)
#define TIM_SR_CC2IF (1u << 2)
#define TIM_SR_CC1OF (1u << 9)

/* ---- EXTI and SYSCFG (RM0090 §12, §9) ---- */
#define EXTI_IMR REG(0x40013C00u)
#define EXTI_FTSR REG(0x40013C0Cu)
#define EXTI_PR REG(0x40013C14u)
#define SYSCFG_EXTICR(n) REG(0x40013808u + 4u * (n))

/* ---- ADC1 and the common ADC registers (RM0090 §13.13), for the internal temperature sensor ---- */
#define ADC1_BASE 0x40012000u
#define ADC1_SR REG(ADC1_BASE + 0x00u)
#define ADC1_CR2 REG(ADC1_BASE + 0x08u)
#define ADC1_SMPR1 REG(ADC1_BASE + 0x0Cu)
#define ADC1_SQR3 REG(ADC1_BASE + 0x34u)
#define ADC1_DR REG(ADC1_BASE + 0x4Cu)
#define ADC_CCR REG(0x40012304u)
#define ADC_SR_EOC (1u << 1)
#define ADC_CR2_ADON (1u << 0)
#define ADC_CR2_SWSTART (1u << 30)
#define ADC_CCR_ADCPRE_DIV4 (1u << 16)
#define ADC_CCR_TSVREFE (1u << 23)
#define TS_CAL1 (*(const volatile uint16_t *)0x1FFF7A2Cu)   /* raw at 30 degC, VDDA 3.3 V (datasheet §6.3.22) */
#define TS_CAL2 (*(const volatile uint16_t *)0x1FFF7A2Eu)   /* raw at 110 degC */

#endif
